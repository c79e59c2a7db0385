"""``vigproc bench hook``: what a host pays per call, the hook as a process vs the in-process API."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path


def cmd_bench_hook(args: argparse.Namespace) -> int:
    """What a host pays per call: the hook as a process vs the in-process API, same frame."""
    import statistics
    import subprocess
    import time

    import numpy as np

    from vigproc.frontends.api import Pipeline
    from vigproc.io.images import write_image

    w, h = args.width, args.height
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (0.5 * np.hypot(w, h)) ** 2
    scene = np.exp(0.2 * rng.standard_normal((h, w)))
    img = np.repeat((0.3 * scene / (1 + r2) ** 2)[..., None], 3, axis=2).astype(np.float32)

    def median_ms(fn) -> tuple[float, float]:
        """Median wall time and median CPU time (this process + children), in ms."""
        ts, cpu = [], []
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), os.times()
            fn()
            c1 = os.times()
            ts.append(time.perf_counter() - t0)
            cpu.append(sum(c1[:4]) - sum(c0[:4]))
        return 1000 * statistics.median(ts), 1000 * statistics.median(cpu)

    from vigproc.frontends import hookserver
    from vigproc.pipeline.processor import Processor, Settings

    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "frame.tif"
        write_image(src, img, bit_depth="float")
        rt = Path(tmp) / "run"
        rt.mkdir(mode=0o700)
        env = {**os.environ, "VIGPROC_PROFILE_DB": str(Path(tmp) / "p.sqlite"), hookserver.ENV_DIR: str(rt)}
        vp = Pipeline("correct", profile="estimate")
        vp.process(img)  # warm-up (kernels loaded)
        api_ms = median_ms(lambda: vp.process(img))
        # the work of a hook estimate call, in a warm process: read, EXIF (its own exiftool), estimate
        def work() -> None:
            with Processor(Settings(mode="estimate", profile="estimate")) as proc:
                proc.process_file(src, Path(tmp) / "w")

        (Path(tmp) / "w").mkdir()
        work()
        work_ms = median_ms(work)

        def hook_call(mode: str, *extra: str, server: str = "off") -> None:
            subprocess.run([sys.executable, "-m", "vigproc.frontends.cli", "hook", "--mode", mode, "--profile", "estimate",
                            *extra, "--", str(src)], env={**env, hookserver.ENV_SWITCH: server}, check=True,
                           capture_output=True)

        est_ms = median_ms(lambda: hook_call("estimate"))
        cor_ms = median_ms(lambda: hook_call("correct", "-o", str(Path(tmp) / "out")))
        start_ms = median_ms(lambda: subprocess.run([sys.executable, "-c", "import vigproc.frontends.cli"], check=True))
        # the warm server: the first call starts it; wait until it answers
        hook_call("estimate", server="on")
        for _ in range(100):
            if any(rt.glob("*.sock")):
                break
            time.sleep(0.1)
        hook_call("estimate", server="on")
        srv_est = median_ms(lambda: hook_call("estimate", server="on"))
        srv_cor = median_ms(lambda: hook_call("correct", "-o", str(Path(tmp) / "out2"), server="on"))
        for sock in rt.glob("*.sock"):
            sock.unlink()  # the server leaves at its next call or idle timeout; nobody finds it now
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"{w}x{h} RGB float32 frame, median of {args.repeat}; {os.cpu_count()} CPUs, load average {load:.1f}")
    print(f"{'':<66}{'wall':>9}    {'CPU':>9}")
    rows = [("API Pipeline.process (correct, in memory, warm)", api_ms),
            ("work of an estimate call, warm process (read, EXIF, estimate)", work_ms),
            ("python -c 'import vigproc.frontends.cli' (interpreter + imports)", start_ms),
            ("hook --mode estimate, new process (VIGPROC_HOOK_SERVER=off)", est_ms),
            ("hook --mode correct -o, new process (VIGPROC_HOOK_SERVER=off)", cor_ms),
            ("hook --mode estimate on the warm server (default)", srv_est),
            ("hook --mode correct -o on the warm server (default)", srv_cor)]
    for label, (ms, cpu) in rows:
        print(f"{label:<66}{ms:>9.1f} ms {cpu:>9.1f} ms")
    print(f"overhead of an estimate call beyond its work: {est_ms[0] - work_ms[0]:.0f} ms in a new process, "
          f"{srv_est[0] - work_ms[0]:.0f} ms on the warm server (CPU: client only)")
    return 0


def hook_arguments(bp: argparse.ArgumentParser) -> None:
    """``vigproc bench hook``'s options."""
    bp.add_argument("--width", type=int, default=1200, help="frame width in px (default %(default)s)")
    bp.add_argument("--height", type=int, default=800, help="frame height in px (default %(default)s)")
    bp.add_argument("--repeat", type=int, default=5, help="timing rounds (default %(default)s)")
    bp.set_defaults(fn=cmd_bench_hook)
