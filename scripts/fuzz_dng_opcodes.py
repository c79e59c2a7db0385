"""Fuzz the DNG opcode-list parser: mutated lists may only give DngOpcodeError.

Seeds: the opcode blobs of ../shared/data/raw/dng_opcodes (when present) and
synthetic lists built here (FixVignetteRadial, RGB and CFA GainMaps, unknown opcodes,
several in one list).  Each round mutates one seed (bit flips, interesting 32-bit
values written at aligned offsets, truncation, extension, chunk insertion, deletion
and duplication, splicing two seeds); half the rounds mutate only one opcode's
parameters and frame the list again with the right sizes, so that the mutation
reaches the opcode decoders rather than the framing.  Then:

* parses it; an accepted list must serialise back to exactly its bytes;
* decodes its vignetting opcodes; each must re-encode to its own bytes;
* evaluates each decoded opcode's gain field on a small frame, and with
  ``--convert-every N`` fits the Kang-Weiss model to every N-th input's calibration
  (:meth:`vigproc.io.dng_vignette.EmbeddedCalibration.fit`).

Anything but :class:`vigproc.io.dng_opcodes.DngOpcodeError` is a failure, as is an input
that takes longer than ``--slow`` seconds.  Failing inputs are saved under ``--crashes``.
The summary (inputs, outcomes, exceptions by type, slowest input, peak memory) is
logged and written as JSON with ``--json``.

Run from the repository root:
    .venv/bin/python scripts/fuzz_dng_opcodes.py --seconds 300 --json fuzz.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import random
import resource
import struct
import sys
import time
import traceback
from collections import Counter
from pathlib import Path

import numpy as np

from vigproc.io.dng_opcodes import DngOpcodeError, parse_opcode_list

log = logging.getLogger("fuzz_dng_opcodes")

SHARED_BLOBS = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "raw" / "dng_opcodes"
INTERESTING_U32 = (0, 1, 2, 3, 4, 7, 8, 9, 16, 56, 0x7F, 0x80, 0xFF, 0x100, 0x7FFF, 0x8000, 0xFFFF,
                   0x10000, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFE, 0xFFFFFFFF)
INTERESTING_F64 = (0.0, -0.0, 1.0, -1.0, 0.5, 1e-300, 1e300, float("inf"), float("-inf"), float("nan"))


def _op(oid: int, params: bytes, version: int = 0x01030000, flags: int = 0) -> bytes:
    return struct.pack(">IIII", oid, version, flags, len(params)) + params


def _gainmap(pv: int, ph: int, mp: int, area=(0, 0, 64, 96), pitch=(1, 1)) -> bytes:
    g = 1.0 + np.random.default_rng(pv * 31 + ph).random((pv, ph, mp))
    return (struct.pack(">iiiiIIII", *area, 0, mp, *pitch)
            + struct.pack(">IIddddI", pv, ph, 1 / max(pv - 1, 1), 1 / max(ph - 1, 1), 0.0, 0.0, mp)
            + g.astype(">f4").tobytes())


def seeds() -> dict[str, bytes]:
    """The corpus: shared blobs plus synthetic lists."""
    out = {}
    if SHARED_BLOBS.is_dir():
        for f in sorted(SHARED_BLOBS.glob("*.bin")):
            out[f"shared/{f.name}"] = f.read_bytes()
    fvr = struct.pack(">7d", 0.4, 0.1, -0.02, 0.0, 0.0, 0.5, 0.5)
    out["synthetic/fvr"] = struct.pack(">I", 1) + _op(3, fvr)
    out["synthetic/gainmap_rgb"] = struct.pack(">I", 1) + _op(9, _gainmap(5, 7, 3))
    out["synthetic/gainmap_cfa"] = struct.pack(">I", 4) + b"".join(
        _op(9, _gainmap(4, 6, 1, area=(t, l, 64, 96), pitch=(2, 2))) for t in (0, 1) for l in (0, 1))
    out["synthetic/mixed"] = struct.pack(">I", 4) + b"".join([
        _op(6, struct.pack(">iiii", 0, 0, 64, 96)), _op(3, fvr, flags=2),
        _op(77, b"unknown opcode", version=0x01060000, flags=1), _op(9, _gainmap(1, 1, 1))])
    out["synthetic/empty"] = struct.pack(">I", 0)
    return out


def mutate(rng: random.Random, data: bytes, corpus: list[bytes]) -> bytes:
    """One to four random mutations of ``data``."""
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        kind = rng.randrange(9)
        n = len(b)
        if kind == 0 and n:  # flip bits
            for _ in range(rng.randint(1, 8)):
                i = rng.randrange(n)
                b[i] ^= 1 << rng.randrange(8)
        elif kind == 1 and n >= 4:  # an interesting uint32 at an aligned offset (counts, sizes, points)
            i = rng.randrange(0, n - 3) & ~3
            b[i:i + 4] = struct.pack(">I", rng.choice(INTERESTING_U32 + (n, n - 4, n + 4)))
        elif kind == 2 and n >= 8:  # an interesting double (coefficients, spacing, origin)
            i = rng.randrange(0, n - 7) & ~3
            b[i:i + 8] = struct.pack(">d", rng.choice(INTERESTING_F64))
        elif kind == 3 and n:  # truncate
            del b[rng.randrange(n):]
        elif kind == 4:  # extend
            b += bytes(rng.randrange(256) for _ in range(rng.choice((1, 3, 4, 16, 64))))
        elif kind == 5 and n:  # insert a chunk
            i = rng.randrange(n + 1)
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.choice((1, 4, 8, 16))))
        elif kind == 6 and n > 1:  # delete a chunk
            i = rng.randrange(n)
            del b[i:i + rng.choice((1, 4, 8, 16))]
        elif kind == 7 and n > 4:  # duplicate a chunk
            i = rng.randrange(n)
            j = min(n, i + rng.choice((4, 16, 64)))
            b[j:j] = b[i:j]
        elif kind == 8:  # splice with another seed
            other = rng.choice(corpus)
            i = rng.randrange(len(b) + 1)
            j = rng.randrange(len(other) + 1)
            b = b[:i] + bytearray(other[j:])
    return bytes(b)


#: What typed errors say, by the first phrase of the message that matches.
CATEGORIES = (
    ("declares", "opcodes but", "count larger than the bytes"),
    ("not even its 4-byte count", "", "shorter than the count"),
    ("16-byte header", "", "opcode header truncated"),
    ("parameter bytes but only", "", "parameter size larger than the bytes"),
    ("bytes follow the last", "", "bytes after the last opcode"),
    ("FixVignetteRadial has", "", "FixVignetteRadial: wrong size"),
    ("five finite", "", "FixVignetteRadial: non-finite coefficient"),
    ("optical centre", "", "FixVignetteRadial: centre outside [0, 1]"),
    ("fewer than its", "", "GainMap: header truncated"),
    ("bytes of gains", "", "GainMap: points do not match its bytes"),
    ("must each be at least 1", "", "GainMap: zero points or planes"),
    ("each must be at least 1", "", "GainMap: zero points or planes"),
    ("GainMap: ", "", "GainMap: invalid area, spacing or gains"),
)


def category(msg: str) -> str:
    for a, b, label in CATEGORIES:
        if a in msg and b in msg:
            return label
    return "other: " + msg.split(": ", 1)[-1][:60]


def mutate_params(rng: random.Random, data: bytes, corpus: list[bytes]) -> bytes:
    """Mutate the parameters of one opcode of a valid list and frame it again with the
    right sizes, so the mutation reaches the opcode's decoder rather than the framing."""
    try:
        lst = parse_opcode_list(data)
    except DngOpcodeError:
        return mutate(rng, data, corpus)
    if not len(lst):
        return mutate(rng, data, corpus)
    ops = list(lst.opcodes)
    i = rng.randrange(len(ops))
    op = ops[i]
    params = mutate(rng, op.params, [o.params for o in ops]) if op.params else op.params
    # keep the header of the real opcode most of the time (its id picks the decoder)
    oid = op.opcode_id if rng.random() < 0.9 else rng.choice((3, 9, rng.randrange(1 << 32)))
    ops[i] = type(op)(oid, op.dng_version, rng.choice((op.flags, 0, 1, 2, 3, 0xFFFFFFFF)), params)
    return type(lst)(tuple(ops)).to_bytes()


def exercise(data: bytes, convert: bool, times: dict[str, float]) -> str:
    """Parse, round-trip, decode and evaluate one input; the outcome's name.  The
    seconds of the parse/evaluate part and of the conversion go into ``times``."""
    t0 = time.perf_counter()
    lst = parse_opcode_list(data, "fuzz input")
    if lst.to_bytes() != data:
        raise AssertionError("an accepted list does not serialise back to its bytes")
    decoded = lst.decoded("fuzz input")
    for i, op in decoded:
        if op.to_opcode().to_bytes() != lst.opcodes[i].to_bytes():
            raise AssertionError(f"decoded {type(op).__name__} does not re-encode to its bytes")
        if hasattr(op, "map_planes"):
            for p in range(min(op.area.plane + op.area.planes, 4)):
                op.gain_field(24, 16, p)
                op.gain_field(24, 16, p, ignore_pitch=False)
        else:
            op.gain_field(24, 16)
    times["parse"] = time.perf_counter() - t0
    if convert and decoded:
        from vigproc.io.dng_vignette import EmbeddedCalibration
        from vigproc.errors import VigprocError

        cal = EmbeddedCalibration.from_lists([("OpcodeList3", lst)], "fuzz input")
        if cal is None:  # only no-op opcodes
            return "accepted"
        t1 = time.perf_counter()
        try:
            cal.fit(48, 32)
        except VigprocError:  # an absurd field (a gain of 0, a blackout) is a typed refusal too
            return "converted-refused"
        finally:
            times["convert"] = time.perf_counter() - t1
        return "converted"
    return "accepted" if decoded or len(lst) else "accepted-empty"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=300.0, help="how long to fuzz (default 300)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ap.add_argument("--slow", type=float, default=1.0,
                    help="seconds of parsing and evaluating beyond which an input counts as a hang (default 1)")
    ap.add_argument("--slow-convert", type=float, default=30.0,
                    help="seconds of one Kang-Weiss fit beyond which it counts as a hang (default 30)")
    ap.add_argument("--convert-every", type=int, default=0, metavar="N",
                    help="also fit the Kang-Weiss model to every N-th input (0: never; a fit takes ~0.1 s)")
    ap.add_argument("--crashes", default="fuzz-crashes", help="folder for failing inputs (default %(default)s)")
    ap.add_argument("--json", help="write the summary here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    corpus_named = seeds()
    corpus = list(corpus_named.values())
    log.info("seeds: %s", ", ".join(f"{k} ({len(v)} B)" for k, v in corpus_named.items()))
    rng = random.Random(args.seed)
    outcomes: Counter[str] = Counter()
    errors: Counter[str] = Counter()
    failures: list[dict] = []
    slowest = (0.0, "")
    slowest_fit = 0.0
    n = 0
    t_end = time.monotonic() + args.seconds
    t0 = time.monotonic()
    while time.monotonic() < t_end:
        if n < len(corpus):
            data = corpus[n]
        elif rng.random() < 0.5:
            data = mutate_params(rng, rng.choice(corpus), corpus)
        else:
            data = mutate(rng, rng.choice(corpus), corpus)
        n += 1
        times = {"parse": 0.0, "convert": 0.0}
        t = time.perf_counter()
        try:
            outcomes[exercise(data, args.convert_every > 0 and n % args.convert_every == 0, times)] += 1
        except DngOpcodeError as exc:
            outcomes["DngOpcodeError"] += 1
            errors[category(str(exc))] += 1
        except Exception as exc:  # noqa: BLE001 - this is what the fuzzer looks for
            name = type(exc).__name__
            outcomes[f"FAIL {name}"] += 1
            digest = hashlib.sha256(data).hexdigest()[:16]
            if len(failures) < 50:
                Path(args.crashes).mkdir(exist_ok=True)
                (Path(args.crashes) / f"{digest}.bin").write_bytes(data)
                failures.append({"type": name, "message": str(exc)[:200], "input": f"{digest}.bin",
                                 "traceback": traceback.format_exc(limit=4)[-800:]})
        dt = time.perf_counter() - t
        if not times["parse"]:  # raised before the parse part ended
            times["parse"] = dt
        if times["parse"] > slowest[0]:
            slowest = (times["parse"], hashlib.sha256(data).hexdigest()[:16])
        slowest_fit = max(slowest_fit, times["convert"])
        if times["parse"] > args.slow or times["convert"] > args.slow_convert:
            outcomes["FAIL slow"] += 1
            Path(args.crashes).mkdir(exist_ok=True)
            (Path(args.crashes) / f"slow-{hashlib.sha256(data).hexdigest()[:16]}.bin").write_bytes(data)
        if n % 20000 == 0:
            log.info("%d inputs, %.0f s: %s", n, time.monotonic() - t0, dict(outcomes))
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    summary = {
        "inputs": n, "seconds": round(time.monotonic() - t0, 1), "seed": args.seed, "convert_every": args.convert_every,
        "seeds": {k: len(v) for k, v in corpus_named.items()},
        "outcomes": dict(outcomes.most_common()),
        "typed_errors_by_kind": dict(errors.most_common()),
        "slowest_parse_seconds": round(slowest[0], 4), "slowest_fit_seconds": round(slowest_fit, 3),
        "peak_rss_mib": round(peak_mib, 1),
        "failures": failures,
    }
    log.info("%s", json.dumps(summary, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1) + "\n")
    return 1 if any(k.startswith("FAIL") for k in outcomes) else 0


if __name__ == "__main__":
    sys.exit(main())
