"""vigproc.forensics.report: the figures of a check's report and the size of its HTML."""

import numpy as np

from benchmarks.synthetic import table1_model
from vigproc.forensics.check import forensic_check, ring_falloff
from vigproc.forensics.report import _EST, ReportItem, report_figure, thumbnail, write_report

from conftest import textured


def _brightening_frame(h=400, w=600):
    """A frame whose fit brightens toward the corners (a scene lit from the edges)."""
    return textured(h, w, seed=3) / table1_model(2).rescale(w, h).field()


def _red_rows(fig: np.ndarray) -> np.ndarray:
    """Rows of the figure's right half (the fall-off plot) drawn in the estimate's colour."""
    right = fig[:, fig.shape[1] // 2 :]
    hit = np.all(np.abs(right - np.asarray(_EST, dtype=np.float32)) < 0.02, axis=2)
    return np.flatnonzero(hit.any(axis=1))


def test_a_fit_that_brightens_the_corners_is_drawn_not_flattened_at_zero():
    """A new user's check showed '+0.24 ... +1.18 EV' in the numbers and a flat red line
    at 0 EV in the plot: values above 0 EV were clipped to the top edge."""
    img = _brightening_frame()
    v = forensic_check(img, None)
    fit = v.estimate.candidate if v.estimate.candidate is not None else v.estimate
    assert ring_falloff(fit, (0.9,))[0] > 0.5  # the premise: a fit that brightens the corners
    fig = report_figure(ReportItem("bright.jpg", v, thumbnail(img)))
    rows = _red_rows(fig)
    # the curve climbs over many rows (the legend's red word is one text line, ~10 rows)
    assert rows.size and rows.max() - rows.min() > 60


def test_the_html_report_is_small(tmp_path):
    """A 48-frame HTML report was 19 MB (a 400 px PNG per frame): one JPEG figure per
    frame with a 320 px thumbnail now, also for a frame of noise-like texture (the worst
    case for compression).  The frame is larger than the thumbnail (block means, then
    resampling), not camera-sized: the thumbnail and the figure have the same size for
    any frame, and a smaller frame's means keep more of its texture, the harder case."""
    img = np.repeat(_brightening_frame(640, 960)[..., None], 3, axis=2)
    v = forensic_check(img, None)
    items = [ReportItem(f"frame{i}.jpg", v, thumbnail(img)) for i in range(4)]
    out = write_report(tmp_path / "r.html", items)
    text = out.read_text()
    assert text.count("data:image/jpeg;base64,") == 4 and "data:image/png" not in text
    assert out.stat().st_size < 4 * 120_000, out.stat().st_size
