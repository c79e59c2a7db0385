"""RAW flat frames measured per CFA plane before demosaicing (issue 41): a Bayer DNG with
known per-plane fields written into its mosaic; ``flat-field`` on it recovers each
plane's field."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from dngfixture import make_dng

rawpy = pytest.importorskip("rawpy")
pytestmark = pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool program not installed")

W, H = 480, 320
#: Per-plane exponents of a cos^k(atan(r/f)) fall-off (R, G, B): a phone module's tint.
K = (4.4, 3.2, 2.2)
FOCAL35 = 26.0
CENTER = (10.0, -6.0)


def plane_log_fields(width: int = W, height: int = H) -> np.ndarray:
    """ln φ_c at the sensor's pixel positions, H×W×3 (R, G, B)."""
    f = FOCAL35 / 21.633 * 0.5 * math.hypot(width, height)
    x = np.arange(width) - (width - 1) / 2 - CENTER[0]
    y = np.arange(height) - (height - 1) / 2 - CENTER[1]
    ln_cos = -0.5 * np.log1p((x[None, :] ** 2 + y[:, None] ** 2) / f**2)
    return np.stack([k * ln_cos for k in K], axis=-1)


def mosaic_field(log_fields: np.ndarray) -> np.ndarray:
    """The per-plane fields as one H×W attenuation of an RGGB mosaic."""
    out = np.empty(log_fields.shape[:2])
    out[0::2, 0::2] = np.exp(log_fields[0::2, 0::2, 0])
    out[0::2, 1::2] = np.exp(log_fields[0::2, 1::2, 1])
    out[1::2, 0::2] = np.exp(log_fields[1::2, 0::2, 1])
    out[1::2, 1::2] = np.exp(log_fields[1::2, 1::2, 2])
    return out


def flat_dng(path: Path, seed: int, gradient: tuple[float, float] = (0.0, 0.0)) -> Path:
    """A flat frame of a white wall (a planar gradient of its light, ln across the frame)
    through the per-plane fields; 0.2 % noise."""
    ramp = np.exp(gradient[0] * (np.arange(W) / W - 0.5)[None, :] + gradient[1] * (np.arange(H) / H - 0.5)[:, None])
    make_dng(path, width=W, height=H, field=mosaic_field(plane_log_fields()), scene=0.8 * ramp / ramp.max(),
             noise=0.002, seed=seed)
    return path


def per_plane_error_ev(model, width: int = W, height: int = H) -> np.ndarray:
    """RMS over the frame of log2(fitted / true) per plane, about its mean (a per-plane
    constant is white balance)."""
    d = (model.channel_log_fields((height, width)) - plane_log_fields(width, height)) / math.log(2)
    d -= d.mean(axis=(0, 1))
    return np.sqrt(np.mean(d * d, axis=(0, 1)))


def test_cfa_flat_field_recovers_each_planes_field(tmp_path: Path) -> None:
    from vigproc.pipeline.cfa_flat import cfa_flat_field

    path = flat_dng(tmp_path / "flat 1.dng", seed=0, gradient=(0.06, -0.04))
    before = path.read_bytes()
    m = cfa_flat_field(path, W, H)
    assert path.read_bytes() == before  # the input is not modified
    assert m is not None and m.size == (W, H)
    assert m.colour is not None and m.colour.source == "flat-field:cfa"
    err = per_plane_error_ev(m)
    assert err.max() < 0.01, err


def test_estimate_of_a_raw_flat_frame_measures_its_planes(tmp_path: Path) -> None:
    """The pipeline (``vigproc estimate --method flat-field`` on a RAW) takes the CFA planes'
    estimate, not the developed frame's."""
    from vigproc.pipeline.processor import Processor
    from vigproc.pipeline.settings import Settings

    path = flat_dng(tmp_path / "-flat;$(x).dng", seed=1, gradient=(-0.05, 0.03))
    with Processor(Settings(mode="estimate", method="flat-field")) as proc:
        res = proc.process_unwritten(path)
    m = res.model
    assert res.source == "estimate" and m.colour is not None and m.colour.source == "flat-field:cfa"
    assert per_plane_error_ev(m, *m.size).max() < 0.01


def test_profile_learned_from_raw_flat_frames_holds_the_planes_fields(tmp_path: Path) -> None:
    """``vigproc profile learn --method flat-field`` on three RAW flat frames: the profile's
    per-plane fields."""
    from vigproc.pipeline.processor import Processor
    from vigproc.pipeline.settings import Settings
    from vigproc.stores.profiles import ProfileStore

    paths = [flat_dng(tmp_path / f"flat{i}.dng", seed=10 + i, gradient=g)
             for i, g in enumerate([(0.08, 0.0), (-0.03, 0.07), (0.02, -0.06)])]
    with ProfileStore(tmp_path / "p.sqlite") as store, \
            Processor(Settings(mode="learn", method="flat-field"), store=store) as proc:
        for p in paths:
            proc.process_unwritten(p)
        (prof,) = store.list()
        m = prof.model(W, H)
    assert prof.n_frames == 3 and m.colour is not None
    assert per_plane_error_ev(m).max() < 0.01


def test_a_raw_without_a_bayer_mosaic_is_left_to_the_developed_frame(tmp_path: Path) -> None:
    from vigproc.pipeline.cfa_flat import cfa_flat_field

    path = tmp_path / "not-raw.dng"
    path.write_bytes(b"II*\x00" + b"\x00" * 64)
    from vigproc.errors import ImageReadError

    with pytest.raises(ImageReadError):
        cfa_flat_field(path, W, H)


def test_estimate_command_on_a_raw_flat_frame(tmp_path: Path) -> None:
    """``vigproc estimate --method flat-field --json`` on a RAW (its half-size path): the
    planes' model, for the full frame."""
    import json

    from conftest import run_cli

    from vigproc.core.model import VignettingModel

    path = flat_dng(tmp_path / "-x flat.dng", seed=2, gradient=(0.04, 0.05))
    r = run_cli("estimate", "--method", "flat-field", "--json", "--", path)
    assert r.returncode == 0, r.stderr
    m = VignettingModel.from_dict(json.loads(r.stdout)["results"][0]["model"])
    assert m.size == (W, H) and m.colour is not None and m.colour.source == "flat-field:cfa"
    assert per_plane_error_ev(m).max() < 0.01
