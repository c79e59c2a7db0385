"""Colour shading from and into DNG files: per-plane GainMaps (issue 41)."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from vigproc.core.colour import ColourField
from vigproc.core.model import VignettingModel
from vigproc.io.dng_opcodes import AreaSpec, GainMap, OpcodeList, parse_opcode_list
from vigproc.io.dng_vignette import EmbeddedCalibration, model_to_gain_maps

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw"
GAINMAP = DATA / "dng_opcodes" / "GainMap.bin"
CFA_DNG = DATA / "tinydng" / "colorchart.dng"


def spec_gain(op: GainMap, width: int, height: int, plane: int) -> np.ndarray:
    """The DNG specification's GainMap gain at every pixel (independent of vigproc's
    implementation): pixel centres at ((row + ½)/H, (col + ½)/W), map index
    (position − origin)/spacing clamped to the map, bilinear interpolation."""
    pv, ph = op.points
    rv = ((np.arange(height) + 0.5) / height - op.origin_v) / op.spacing_v
    rh = ((np.arange(width) + 0.5) / width - op.origin_h) / op.spacing_h
    R, C = np.meshgrid(np.clip(rv, 0, pv - 1), np.clip(rh, 0, ph - 1), indexing="ij")
    g = op.gains[:, :, min(plane, op.map_planes - 1)].astype(np.float64)
    return map_coordinates(g, [R, C], order=1, mode="nearest")


def _real_map() -> GainMap:
    if not GAINMAP.exists():
        pytest.skip(f"{GAINMAP} is absent (the shared data set)")
    (_, op), = parse_opcode_list(GAINMAP.read_bytes(), "GainMap.bin").decoded()
    return op


def test_rgb_gain_map_applied_per_plane_as_the_spec_says():
    op = _real_map()
    W, H = 507, 380  # the map's 4056x3040 frame at 1/8
    cal = EmbeddedCalibration.from_lists([("OpcodeList3", OpcodeList((op.to_opcode(),)))], "GainMap.bin")
    m = cal.model(W, H)
    assert m.colour is not None and m.colour.source == "dng:GainMap"
    img = np.full((H, W, 3), 0.25, dtype=np.float32)
    out = m.correct_image(img)
    for c in range(3):
        want = 0.25 * spec_gain(op, W, H, c)
        d = np.log2(out[..., c] / want)
        assert np.sqrt(np.mean(d * d)) < 0.005 and np.abs(d).max() < 0.005
    # the planes differ (R's corner gain is the largest): not one luminance field for all
    assert out[0, 0, 0] / out[0, 0, 2] > 1.1


def _cfa_maps(colours):
    # four phases of a 2x2 pattern, each with its own constant gain
    maps = []
    for r in range(2):
        for c in range(2):
            g = np.full((3, 3), 1.0 + 0.1 * (2 * r + c + 1), dtype=np.float32)
            maps.append(GainMap(AreaSpec(r, c, 40, 60, 0, 1, 2, 2), g, 0.5, 0.5))
    return EmbeddedCalibration.from_lists([("OpcodeList2", OpcodeList(tuple(m.to_opcode() for m in maps)))],
                                          "cfa", cfa_pattern=colours)


def test_cfa_phases_go_to_their_colour():
    cal = _cfa_maps(((0, 1), (1, 2)))
    assert cal.per_plane
    lg = [float(np.exp(cal.log_gain(60, 40, c)).mean()) for c in range(3)]
    # R: phase (0,0) gain 1.1; G: phases (0,1) and (1,0), 1.2 and 1.3 (geometric mean); B: 1.4
    np.testing.assert_allclose(lg, [1.1, math.sqrt(1.2 * 1.3), 1.4], rtol=1e-6)
    # pattern unknown: every channel the mean of the four phases, as before
    blind = _cfa_maps(None)
    assert not blind.per_plane
    g = float(np.exp(blind.log_gain(60, 40, 0)).mean())
    np.testing.assert_allclose(g, (1.1 * 1.2 * 1.3 * 1.4) ** 0.25, rtol=1e-6)


def _colour_model(w, h):
    cf = ColourField(w, h, (20.0, -10.0), [[0.12, 0.05, 0.0], [0.0, 0.0, 0.0], [-0.15, 0.0, 0.02]])
    return VignettingModel(w, h, center=(20.0, -10.0), p=(1 / 1500**2, 0.0, 1 / 1500**2), colour=cf,
                           method="flat-field")


@pytest.mark.parametrize("pattern", [((0, 1), (1, 2)), None])
def test_written_gain_maps_reproduce_the_model(pattern):
    w, h = 600, 400
    m = _colour_model(w, h)
    maps = model_to_gain_maps(m, cfa_pattern=pattern)
    assert len(maps) == (4 if pattern else 1)
    cal = EmbeddedCalibration.from_lists([("OpcodeList2", OpcodeList(tuple(g.to_opcode() for g in maps)))],
                                         "written", cfa_pattern=pattern)
    want = -m.channel_log_fields()
    for c in range(3):
        d = (cal.log_gain(w, h, c) - want[..., c]) / math.log(2)
        assert np.abs(d).max() < 0.002


def test_dng_written_with_per_plane_gain_maps_reads_back(tmp_path):
    if not CFA_DNG.exists():
        pytest.skip(f"{CFA_DNG} is absent (the shared data set)")
    from vigproc.io.dng_vignette import read_embedded, write_dng_correction
    from vigproc.io.metadata import exiftool_path

    try:
        exiftool_path()
    except Exception as exc:  # noqa: BLE001 - any reason exiftool cannot run
        pytest.skip(f"exiftool unavailable: {exc}")
    src = tmp_path / "in.dng"
    shutil.copyfile(CFA_DNG, src)
    before = src.read_bytes()
    w, h = 1734, 1156  # the frame rawpy develops
    info = write_dng_correction(src, tmp_path / "out.dng", _colour_model(w, h))
    assert src.read_bytes() == before
    assert info["list"] == "OpcodeList2" and info["opcode"]["maps"] == 4
    cal = read_embedded(tmp_path / "out.dng")
    assert cal.cfa_pattern == ((0, 1), (1, 2)) and cal.per_plane
    m = cal.model(w, h)
    assert m.colour is not None
    r = m.colour.ratios(64, 43)
    assert r[0, 0, 0] > 1.03 and r[0, 0, 2] < 0.97  # the written tint, read back
