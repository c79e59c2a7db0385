"""``vigproc bench faults``: the watch-folder daemon with its output on a disk that fills.

The output folder (with the daemon's journal and status file, where they live by
default) is a small tmpfs; healthy camera JPEGs are dropped into the watch folder,
the tmpfs fills, the daemon is killed with SIGKILL and restarted while it is full,
the tmpfs is grown (``mount -o remount,size=...``), and it is killed again while it
catches up.  Then the files on disk are counted:

* **inputs**: healthy photos dropped in;
* **outputs**: results of an input on disk -- its JSON sidecar, recording the
  input's content, and the corrected image the sidecar names (none when the
  evidence was too weak to correct: ``--unapplied skip``); ``exactly one``: inputs
  with one complete result, ``duplicates``: results beyond one per input, and images
  no sidecar names;
* **quarantined**: inputs the journal quarantined, or found in the quarantine folder;
* **moved**: inputs no longer at their place in the watch folder;
* **lost**: inputs whose content is nowhere any more (watch or quarantine folder).

Target (issue 22): every input exactly one output, none quarantined, none moved,
0 lost.  Needs root (``mount -t tmpfs``); otherwise it says why it cannot run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from vigproc.errors import VigprocError

log = logging.getLogger(__name__)

#: Where the shared camera JPEGs are, next to the repository.
DEFAULT_IMAGES = Path(__file__).resolve().parents[2] / "shared" / "data" / "jpeg_exif"


class FaultBenchError(VigprocError):
    """The benchmark cannot run here (not root, no tmpfs, no images)."""


@dataclass
class FaultFigures:
    """What one run left on disk (see the module docstring)."""

    inputs: int = 0
    outputs: int = 0
    exactly_one: int = 0
    duplicates: int = 0
    corrected_images: int = 0
    quarantined: int = 0
    moved: int = 0
    lost: int = 0
    attempts_charged: int = 0  # journal attempts + crashes of the inputs (0: nothing charged to a photo)
    kills: int = 0
    pauses: int = 0  # "disk-full" events: the daemon paused
    resumes: int = 0
    temporaries: int = 0  # temporary files left in the output folder
    status_while_full: str = ""  # what the status file said while the disk was full
    resume_s: float = 0.0  # seconds from growing the disk to the daemon resuming (no restart)
    seconds: float = 0.0
    small_mb: int = 0
    grown_mb: int = 0
    notes: list[str] = field(default_factory=list)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def pick_images(folder: Path, n: int, min_mp: float = 1.0, max_mp: float = 4.5) -> list[Path]:
    """``n`` camera JPEGs of ``min_mp``..``max_mp`` megapixels under ``folder`` (by name:
    the same ones every run), with distinct content."""
    import OpenImageIO as oiio

    out, seen = [], set()
    for p in sorted(folder.rglob("*")):
        if p.suffix.lower() not in (".jpg", ".jpeg") or not p.is_file():
            continue
        inp = oiio.ImageInput.open(str(p))
        if inp is None:
            continue
        spec = inp.spec()
        inp.close()
        mp = spec.width * spec.height / 1e6
        digest = _sha(p)
        if min_mp <= mp <= max_mp and digest not in seen:
            seen.add(digest)
            out.append(p)
        if len(out) == n:
            break
    return out


def why_not() -> str | None:
    """Why this machine cannot run the benchmark, or None."""
    if os.name != "posix" or not Path("/proc/mounts").exists():
        return "it needs Linux (tmpfs mounts)"
    if os.geteuid() != 0:
        return "it needs root, to mount the small tmpfs that fills (mount -t tmpfs)"
    probe = Path(tempfile.mkdtemp(prefix="vigproc-tmpfs-probe-"))
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(probe)], capture_output=True,
                           text=True)
        if r.returncode != 0:
            return f"mount -t tmpfs failed here: {r.stderr.strip() or r.returncode}"
        subprocess.run(["umount", str(probe)], check=False, capture_output=True)
        return None
    except OSError as exc:
        return f"cannot run mount: {exc.strerror or exc}"
    finally:
        shutil.rmtree(probe, ignore_errors=True)


class _Watch:
    """``vigproc watch`` as a subprocess, its JSON log in a file on the real disk."""

    def __init__(self, args: list[str], log_file: Path) -> None:
        self.args, self.log_file = args, log_file
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        with open(self.log_file, "ab") as fh:
            self.proc = subprocess.Popen(self.args, stdout=subprocess.DEVNULL, stderr=fh)

    def kill9(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=60)

    def stop(self) -> int:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout=300)

    def events(self) -> list[dict[str, Any]]:
        out = []
        for line in self.log_file.read_bytes().decode("utf-8", "replace").splitlines():
            if line.startswith("{"):
                try:
                    out.append(json.loads(line))
                except ValueError:  # a line cut by SIGKILL
                    pass
        return out

    def count(self, event: str) -> int:
        return sum(ev.get("event") == event for ev in self.events())

    def wait_for(self, what: str, pred: Callable[[], bool], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred():
                return
            if self.proc is not None and self.proc.poll() is not None:
                raise FaultBenchError(f"the daemon exited (code {self.proc.returncode}) while waiting for {what}; "
                                      f"see {self.log_file}")
            time.sleep(0.1)
        raise FaultBenchError(f"timed out after {timeout:.0f} s waiting for {what}; see {self.log_file}")


def _mount(mnt: Path, mb: int, remount: bool = False) -> None:
    opts = f"remount,size={mb}m" if remount else f"size={mb}m,mode=0755"
    cmd = ["mount", "-o", opts, str(mnt)] if remount else ["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(mnt)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise FaultBenchError(f"{' '.join(cmd)} failed: {r.stderr.strip()}")


def _status(out_dir: Path) -> dict[str, Any]:
    """The daemon's status file (a half-written one, on a full disk, reads as empty)."""
    for p in out_dir.glob(".vigproc-watch-*.status.json"):
        try:
            d = json.loads(p.read_text())
            return d if isinstance(d, dict) else {}
        except (OSError, ValueError):
            pass
    return {}


def _results(out_dir: Path) -> tuple[dict[str, list[str | None]], set[str]]:
    """Input (relative path, as its sidecar records it) -> the image each of its complete
    results names (None: the sidecar alone, nothing applied); and every image named."""
    by_input: dict[str, list[str | None]] = {}
    named: set[str] = set()
    for sc in out_dir.glob("*.vigproc.json"):
        try:
            d = json.loads(sc.read_text())
        except (OSError, ValueError):
            continue
        out = d.get("output")
        if not isinstance(d.get("input"), str) or (out is not None and not os.path.isfile(out)):
            continue  # not one of the daemon's, or its image is missing: not a complete result
        by_input.setdefault(d["input"], []).append(out)
        if out is not None:
            named.add(os.path.basename(out))
    return by_input, named


def run_faults(images: list[Path], *, workers: int = 2, small_mb: int = 20, grow_mb: int = 1024, kills: int = 3,
               tmp: str | None = None, timeout: float = 900.0, keep: bool = False) -> FaultFigures:
    """Run the daemon through a filling and grown tmpfs with ``kills`` SIGKILLs (about
    half while the disk is full, the rest while it catches up); count what is left."""
    from vigproc.stores.journal import Journal

    fig = FaultFigures(inputs=len(images), small_mb=small_mb, grown_mb=grow_mb)
    base = Path(tempfile.mkdtemp(prefix="vigproc-bench-faults-", dir=tmp))
    in_dir, out_dir, qdir = base / "in", base / "out", base / "quarantine"
    in_dir.mkdir()
    out_dir.mkdir()
    mounted = False
    watch: _Watch | None = None
    t0 = time.monotonic()
    try:
        _mount(out_dir, small_mb)
        mounted = True
        watch = _Watch([sys.executable, "-m", "vigproc.frontends.cli", "watch", str(in_dir), "-o", str(out_dir),
                        "--workers", str(workers), "--settle", "0.3", "--quarantine", str(qdir),
                        "--profile", "estimate", "--profile-db", str(base / "profiles.sqlite"),
                        "--output-format", "tiff16", "--unapplied", "skip",  # the protocol as measured before issue 38
                        "--retry-base", "1", "--retry-cap", "8", "--log-json"],
                       base / "daemon.log")
        watch.start()
        names = {}
        for i, src in enumerate(images):  # dropped in by rename, each complete when it appears
            rel = f"{i:02d} {src.name}"
            part = in_dir / (rel + ".part")
            shutil.copyfile(src, part)
            os.rename(part, in_dir / rel)
            names[rel] = _sha(in_dir / rel)
        journal = out_dir / ".vigproc-watch.sqlite"

        def done() -> int:
            return len(_results(out_dir)[0])

        k_full = (kills + 1) // 2
        for _ in range(k_full):  # killed while the disk is full (paused; a probe or the last files in progress)
            n = watch.count("disk-full")
            watch.wait_for("the output disk to fill (a disk-full pause)", lambda: watch.count("disk-full") > n, 300)
            time.sleep(3.0)  # paused, probing
            watch.kill9()
            fig.kills += 1
            watch.start()
        n = watch.count("disk-full")
        watch.wait_for("the disk full again after the restart", lambda: watch.count("disk-full") > n, 300)
        watch.wait_for("the status to say paused", lambda: _status(out_dir).get("state") == "paused", 30)
        fig.status_while_full = _status(out_dir).get("paused", {}).get("why", "")
        time.sleep(3.0)
        _mount(out_dir, grow_mb, remount=True)  # the operator grows the disk, the daemon running
        t_grow = time.monotonic()
        watch.wait_for("the daemon to resume on its own", lambda: watch.count("disk-resumed") > 0, 120)
        fig.resume_s = round(time.monotonic() - t_grow, 1)
        for _ in range(kills - k_full):  # killed while it catches up
            n = done()
            watch.wait_for("progress after the disk was grown", lambda: done() > n or done() == len(images), 300)
            watch.kill9()
            fig.kills += 1
            watch.start()
        watch.wait_for("every input done", lambda: done() == len(images), timeout)
        time.sleep(1.0)  # anything wrongly still in flight shows up
        code = watch.stop()
        if code != 0:
            fig.notes.append(f"daemon exit code after SIGTERM: {code}")
        fig.seconds = round(time.monotonic() - t0, 1)

        # ---- the count, from what is on disk
        results, named = _results(out_dir)
        fig.outputs = sum(len(results.get(rel, [])) for rel in names)
        fig.exactly_one = sum(len(results.get(rel, [])) == 1 for rel in names)
        images = [p.name for p in out_dir.iterdir() if p.is_file() and not p.name.startswith(".")
                  and not p.name.endswith(".vigproc.json")]
        fig.corrected_images = sum(name in named for name in images)
        fig.duplicates = fig.outputs - fig.exactly_one + sum(name not in named for name in images)
        fig.temporaries = sum(1 for p in out_dir.iterdir() if p.name.startswith(".") and ".tmp" in p.name)
        in_quarantine = {_sha(p) for p in qdir.iterdir() if p.is_file() and not p.name.endswith(".reason.json")} \
            if qdir.is_dir() else set()
        still = {rel: (in_dir / rel).is_file() and _sha(in_dir / rel) == digest for rel, digest in names.items()}
        fig.moved = sum(not ok for ok in still.values())
        fig.lost = sum(not still[rel] and digest not in in_quarantine for rel, digest in names.items())
        with Journal(journal, job=f"watch:correct:{in_dir.resolve()}->{out_dir.resolve()}") as j:
            entries = {os.path.relpath(e.path, in_dir.resolve()): e for e in j.entries()}
        fig.quarantined = sum(1 for rel in names if (e := entries.get(rel)) is not None and e.state == "quarantined")
        fig.quarantined = max(fig.quarantined, len(in_quarantine))
        fig.attempts_charged = sum(e.attempts + e.crashes for rel, e in entries.items() if rel in names)
        fig.pauses, fig.resumes = watch.count("disk-full"), watch.count("disk-resumed")
        return fig
    finally:
        if watch is not None and watch.proc is not None and watch.proc.poll() is None:
            watch.proc.kill()
            watch.proc.wait()
        if mounted:
            subprocess.run(["umount", "-l", str(out_dir)], check=False, capture_output=True)
        if keep:
            print(f"kept {base} (the daemon's log: {base / 'daemon.log'}; the tmpfs is unmounted)")
        else:
            shutil.rmtree(base, ignore_errors=True)


def cmd_bench_faults(args: argparse.Namespace) -> int:
    """Print the fault run's figures (see the module docstring)."""
    reason = why_not()
    if reason is not None:
        raise FaultBenchError(f"bench faults cannot run here: {reason}")
    folder = Path(args.images or DEFAULT_IMAGES)
    if not folder.is_dir():
        raise FaultBenchError(f"no image folder {folder} (pass --images DIR of camera JPEGs)")
    images = pick_images(folder, args.files)
    if len(images) < args.files:
        raise FaultBenchError(f"only {len(images)} camera JPEGs of 1-4.5 MP under {folder}; need {args.files}")
    mb = sum(p.stat().st_size for p in images) / 1e6
    print(f"{len(images)} camera JPEGs ({mb:.1f} MB) from {folder} -> 16-bit TIFF; output folder, journal and "
          f"status on a {args.small} MB tmpfs grown to {args.grow} MB; {args.workers} workers; {args.kills} kill -9")
    fig = run_faults(images, workers=args.workers, small_mb=args.small, grow_mb=args.grow, kills=args.kills,
                     tmp=args.tmp, keep=args.keep)
    if args.json:
        print(json.dumps(asdict(fig), indent=1))
        return 0
    print(f"inputs {fig.inputs}, outputs {fig.outputs} (exactly one: {fig.exactly_one}, duplicates "
          f"{fig.duplicates}; {fig.corrected_images} corrected images, the rest too weak to correct: sidecar only), "
          f"quarantined {fig.quarantined}, moved out of the input folder {fig.moved}, lost {fig.lost}")
    print(f"attempts or crashes charged to the photos {fig.attempts_charged}; kill -9 {fig.kills}; disk-full pauses "
          f"{fig.pauses}, resumes {fig.resumes} (status while full: 'paused', {fig.status_while_full!r}; resumed "
          f"{fig.resume_s:.1f} s after the disk was grown, no restart); temporaries left {fig.temporaries}; "
          f"{fig.seconds:.0f} s")
    for note in fig.notes:
        print(f"note: {note}")
    target = (fig.exactly_one == fig.inputs and fig.duplicates == 0 and fig.quarantined == 0 and fig.moved == 0
              and fig.lost == 0)
    print("target (every input exactly one output, none quarantined, none moved, 0 lost): "
          + ("met" if target else "NOT met"))
    return 0 if target else 1
