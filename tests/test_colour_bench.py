"""``vigproc bench colour`` (issue 41): the flat part's pieces on one lens, the command's parts."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from benchmarks import colour as B


def test_physical_field_is_cos_k_of_the_chief_ray_angle():
    lf = B.physical_field(24.0, (4.0, 3.0, 2.0), width=480, height=320)
    theta = np.arctan(B.HALF_DIAGONAL_35 / 24.0)  # at the frame's corner (pixel centre ~ corner)
    np.testing.assert_allclose(lf[0, 0], [k * np.log(np.cos(theta)) for k in (4.0, 3.0, 2.0)], rtol=0.01)
    assert np.all(lf[160, 240] > -1e-4)


def test_flat_part_recovers_a_tinted_lens_and_corrects_a_base():
    lens = B.physical_fields()[2]  # phone-26mm
    rng = np.random.default_rng(0)
    base = np.clip(0.3 + 0.1 * rng.standard_normal((B.HEIGHT, B.WIDTH, 3)), 0.05, 1.0)
    (row,) = B.run_flat([lens], [base])
    assert row.colour_found
    assert max(row.field_ev) < 0.01 and max(row.bases_ev) < 0.01
    assert row.de_corrected[0] < 1.0 < row.de_luminance_only[0]  # the tint is what colour removes
    assert max(row.luminance_only_ev) > 5 * max(row.field_ev)


def test_dng_part_matches_the_spec():
    rows = B.run_dng(sizes=((240, 160),))
    if not rows:
        import pytest

        pytest.skip(f"{B.GAINMAP} is absent (the shared data set)")
    (r,) = rows
    assert max(r.spec_max_ev) < 0.005 and max(r.written_max_ev) < 0.01


def test_the_detect_part_runs_the_detection_report(tmp_path, monkeypatch, capsys):
    """``bench colour --part detect`` is ``bench colour-detect``'s report with its defaults
    (the report itself: tests/test_colour_cast.py); its figures land in the JSON."""
    import json

    from benchmarks.cli import colour_detect
    from vigproc.frontends import cli

    seen = []

    def report(args):
        seen.append(args)
        print("detect table")
        return 0, {"rate_at_5": 0.5}

    monkeypatch.setattr(colour_detect, "bench_detect_report", report)
    out = tmp_path / "c.json"
    assert cli.main(["bench", "colour", "--part", "detect", "--json", str(out)]) == 0
    assert len(seen) == 1 and "detect table" in capsys.readouterr().out
    assert json.loads(out.read_text())["detect"] == {"rate_at_5": 0.5}


def test_flat_part_measures_the_grid_field_too():
    """The grid field (a flat-field profile holding the measured field) is scored beside the
    Kang-Weiss profile: on a physical lens it holds the field as well."""
    lens = B.physical_fields()[2]
    rng = np.random.default_rng(1)
    base = np.clip(0.3 + 0.1 * rng.standard_normal((B.HEIGHT, B.WIDTH, 3)), 0.05, 1.0)
    (row,) = B.run_flat([lens], [base])
    assert max(row.grid_ev) < 0.005 and max(row.grid_bases_ev) < 0.005
    assert row.de_grid[0] < 1.0 < row.de_uncorrected[0]
