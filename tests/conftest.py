"""Shared fixtures: small synthetic images with known vignetting, and the shared data path."""

from __future__ import annotations

import contextlib
import io
import logging
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pytest_configure(config):
    """Compile the Numba kernels once, before pytest-xdist's workers start: two workers
    compiling the same cached kernel at once can race on Numba's cache files (a fresh
    clone has none), and each would pay for the compile.  The kernels are split over
    two processes (this one and :func:`_warm_codes` in a child), one per core, each
    compiling its own kernels only, so that no two processes write one kernel's cache."""
    if hasattr(config, "workerinput"):  # a worker: the main process has done it
        return
    _blas_threads_for_workers(config)
    import vigproc
    from vigproc.core._kernels import codes, field

    # log φ on a grid is called by the child's corrections too: compiled here first (all
    # three array layouts the estimators and lyu2010's reversed border strips pass), so
    # that the child only loads it from the cache
    xs, ys = np.linspace(-1.0, 1.0, 8), np.linspace(-1.0, 1.0, 6)
    alpha = np.zeros(7)
    for sx, sy in ((xs, ys), (xs[::-1][:4], ys), (xs, ys[::-1][:3])):
        field.log_field_grid(sx, sy, 0.0, 0.0, 1e-4, 0.0, 1e-4, alpha, np.empty((sy.shape[0], sx.shape[0])))
    child = None
    if not all(os.path.exists(k._cache._cache_file._index_path)  # noqa: SLF001 - Numba's cache index
               for k in (codes.reduce_codes, codes.correct_codes, field.log_field_grid_parallel)):
        # the child imports the vigproc this process imported (Numba caches by source file)
        here = str(Path(vigproc.__file__).resolve().parents[1])
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [here, os.environ.get("PYTHONPATH")]))}
        child = subprocess.Popen([sys.executable, "-c", "import conftest; conftest._warm_codes()"],
                                 cwd=Path(__file__).parent, env=env)
    try:
        img = textured(96, 144, seed=0, contrast=0.1)
        # the default method fits the fall-off's centre (the geometry kernels) only where the
        # fall-off is deep enough (here 2.1 EV at the corners): else each worker compiled them
        deep = img * vigproc.VignettingModel(144, 96, p=(6e-4, 0.0, 6e-4)).field()
        for method, frame in (("default", img), ("default", deep), ("robust", img), ("lens-family", img),
                              ("flat-field", img), ("ga", textured(64, 96))):
            try:
                vigproc.estimate(frame, method, channel_axis=None)
            except vigproc.VigprocError:  # warm-up only: the tests judge the estimators
                pass
        vigproc.correct(np.repeat(img[..., None], 3, axis=2).astype(np.float32),
                        vigproc.VignettingModel(144, 96, p=(1e-4, 0.0, 1e-4)))
        # the pooled nulls' draws (forensics): a kernel of its own
        from vigproc.forensics.lensmatch import pooled_d2, pooled_null

        pooled_null(np.zeros((4, 1)), np.arange(4), 2, pooled_d2, seed=0, draws=2)
    finally:
        if child is not None:
            child.wait()


def _blas_threads_for_workers(config) -> None:
    """Give each pytest-xdist worker's BLAS (OpenBLAS, under NumPy and SciPy) its share of
    the cores, in the environment the workers and the processes they start inherit: an
    OpenBLAS thread waits for work by spinning, so two workers each with a thread per
    core took the cores from each other (docs/benchmarks/tests.md: "BLAS threads").  A
    value the caller set is kept; a run in one process is left alone."""
    workers = len(config.getoption("tx", None) or []) if config.getoption("dist", "no") != "no" else 0
    if workers:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // workers)))


def _warm_codes() -> None:
    """The kernels of display-encoded frames (8- and 16-bit codes: binning and correction)
    and of full-frame fields, compiled in a child of :func:`pytest_configure`."""
    from vigproc.core._kernels.field import log_field_grid_parallel
    from vigproc.core.correct import correct_codes
    from vigproc.core.model import VignettingModel
    from vigproc.core.pixels import reduce_codes
    from vigproc.io.images import EncodedImage, encode_steps

    m = VignettingModel(144, 96, p=(1e-4, 0.0, 1e-4))
    for depth, top in (("uint8", 255), ("uint16", 65535)):
        # the tables the pipeline passes (read-only: Numba compiles another signature for those)
        frame = EncodedImage((np.arange(96 * 144 * 3) % top).astype(depth).reshape(96, 144, 3), "srgb")
        reduce_codes(frame.codes, frame.decode_table(), 4)
        correct_codes(frame.codes, m, frame.decode_table(), encode_steps("srgb", depth))
    correct_codes(frame.codes.astype(np.uint8), m, frame.decode_table()[:256], encode_steps("srgb", "uint16"))
    xs, ys = np.linspace(-1.0, 1.0, 8), np.linspace(-1.0, 1.0, 6)
    log_field_grid_parallel(xs, ys, 0.0, 0.0, *m.p, np.asarray(m.alpha, dtype=np.float64), np.empty((6, 8)))


def textured(h: int, w: int, seed: int = 0, contrast: float = 0.3) -> np.ndarray:
    """A positive 'natural-like' texture: log-normal with 1/f-ish smoothing."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(h, w))
    f = np.fft.rfft2(noise)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f /= np.maximum(np.hypot(fx, fy), 1.0 / max(h, w)) ** 0.9
    tex = np.fft.irfft2(f, s=(h, w))
    tex = contrast * tex / tex.std()
    return 0.4 * np.exp(tex)


def coloured_scene(h: int, w: int, seed: int = 0, contrast: float = 0.05, patches: int = 12) -> np.ndarray:
    """An H×W×3 scene as a photograph's: one texture (its shading) over patches of
    different colour (surfaces), so that R, G and B change together inside a patch
    and differently across a patch's edge."""
    rng = np.random.default_rng(seed + 10_000)
    tex = textured(h, w, seed=seed, contrast=contrast)
    sites = rng.random((patches, 2)) * (h, w)
    yy, xx = np.mgrid[0:h, 0:w]
    nearest = np.argmin((yy[..., None] - sites[:, 0]) ** 2 + (xx[..., None] - sites[:, 1]) ** 2, axis=-1)
    albedo = rng.uniform(0.3, 1.0, size=(patches, 3))
    return tex[..., None] * albedo[nearest]


def chromatic_glow(h: int, w: int, strength: float = 0.6) -> np.ndarray:
    """Log gains (H×W×3) of a scene's own light that changes colour as it brightens:
    a warm glow from one side of the frame (R most, B least), as a low sun or a lamp
    throws; no lens does this."""
    x = np.linspace(-1.0, 1.0, w)[None, :]
    y = np.linspace(-1.0, 1.0, h)[:, None]
    g = np.exp(-((x - 0.6) ** 2 + (y + 0.3) ** 2) / 0.5)
    return strength * g[..., None] * np.array([1.0, 0.55, 0.15])


def photo_like(h: int, w: int, seed: int = 0, contrast: float = 0.05) -> np.ndarray:
    """A texture that, like a real photograph, carries the average scene fall-off of
    natural photos (:mod:`vigproc.core.scene`), which the default estimator divides out."""
    from vigproc.core.scene import default_scene_falloff

    return textured(h, w, seed=seed, contrast=contrast) * default_scene_falloff().model(w, h).field()


def run_cli(*args, cwd=None) -> subprocess.CompletedProcess:
    """``vigproc ARGS`` in this process, for tests not about the process boundary (a new
    process costs a second of start-up): ``main(argv)`` with stdout and stderr encoded
    as a subprocess's and decoded as ``subprocess.run(..., text=True)`` decodes them, a
    usage error's exit code included.  Returns what ``subprocess.run`` would; an
    exception that would end the process with a traceback propagates (the test fails)."""
    from vigproc.frontends.cli import main

    out, err = io.BytesIO(), io.BytesIO()
    streams = [io.TextIOWrapper(b, encoding=std.encoding, errors=std.errors, write_through=True)
               for b, std in ((out, sys.__stdout__), (err, sys.__stderr__))]
    root, here = logging.getLogger(), os.getcwd()
    handlers, level = root.handlers[:], root.level
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(streams[0]), \
                contextlib.redirect_stderr(streams[1]):
            if cwd is not None:
                os.chdir(cwd)
            try:
                code = main([str(a) for a in args])
            except SystemExit as exc:  # argparse's usage errors and --help
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            for s in streams:
                s.flush()
    finally:
        os.chdir(here)
        root.handlers[:], root.level = handlers, level
        logging.captureWarnings(False)
    return subprocess.CompletedProcess(args, code, out.getvalue().decode(), err.getvalue().decode())


@pytest.fixture
def shared_data() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"shared data not present at {SHARED}")
    return SHARED


@pytest.fixture(autouse=True)
def _private_profile_store(tmp_path_factory, monkeypatch):
    """Commands default to ``--profile auto``, which opens the user's profile store:
    each test gets its own (inherited by the subprocesses it starts), so the suite
    never reads or writes the store of the person running it.  Tests that want a
    particular store set VIGPROC_PROFILE_DB themselves."""
    monkeypatch.setenv("VIGPROC_PROFILE_DB", str(tmp_path_factory.mktemp("store") / "profiles.sqlite"))


@pytest.fixture(autouse=True)
def _no_hook_server(monkeypatch):
    """`vigproc hook` starts a warm background server for the calls that follow
    (vigproc.frontends.hookserver); the suite runs every call in-process unless a test asks for
    the server itself (tests/test_hookserver.py), so no test leaves a process behind."""
    monkeypatch.setenv("VIGPROC_HOOK_SERVER", "off")
