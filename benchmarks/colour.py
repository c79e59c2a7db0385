"""``vigproc bench colour --part flat``: colour shading from flat frames and DNG gain maps.

Per-channel fields (the truth)
------------------------------
* **Physical** (:func:`physical_fields`): a sensor whose microlenses and filter stack
  pass channel c in proportion to T_c(θ) = cos^k_c θ of the chief-ray angle
  θ = atan(r / f), r the distance from the optical centre and f the focal length in
  the same units (a thin-lens exit pupil at f: the chief ray's angle). The whole
  fall-off of channel c is T_c(θ), the cos^4 law for k_c = 4; k_R ≠ k_G ≠ k_B tints
  the corners (k_R > k_G: red falls faster, the corners turn cyan). Settings: focal
  lengths in 35-mm terms on the 3:2 frame (half-diagonal 21.63 mm), exponents
  chosen to span what wide lenses on mirrorless bodies and phone modules show
  (corner R/G and B/G of 0.1-0.4 EV), one off-centre optical axis, and one neutral
  lens (all k equal) that must come out colourless.
* **Real** (:func:`gainmap_fields`): the per-plane GainMap in
  ``../shared/data/raw/dng_opcodes/GainMap.bin`` (a measured lens-shading map of an
  IMX477 sensor; no licence stated: internal benchmarking only), φ_c = 1/g_c at the
  frame's pixel centres (the map is in relative coordinates: its 4:3 frame is
  stretched onto 3:2).

Protocol (flat)
---------------
For each field, 3 flat frames of 480×320 px: a wall of colour (0.9, 1, 0.8) (white
balance: a per-channel constant) × φ_c × a planar illumination gradient of up to
±``GRADIENT`` (natural log) across the frame in a random direction × (1 + 1 % noise).
Each is estimated with ``flat-field`` and learned into a temporary profile store (as
``vigproc profile learn --method flat-field`` does); the profile's model (luminance
and colour) is then

* compared with the truth: per channel the RMS over the frame of log2(φ̂_c / φ_c)
  about its mean (a per-channel constant is white balance), in EV;
* applied (:func:`vigproc.core.correct.correct`) to the vignetting-free bases (central
  crops of camera frames, as ``bench clean``) multiplied by φ_c: the same RMS of
  log2(corrected / base), median over the bases;
* judged on a grey patch (18 % linear grey, 16×16 px) at each corner against the
  same patch at the centre: the worst corner's CIEDE2000 (sRGB primaries, D65), after
  correction and uncorrected; and the same with the corner's luminance equalised to
  the centre's (the tint alone).

The profile also holds the frames' **grid field** (:mod:`vigproc.pipeline.flat_grid`: each
frame's gradient removed about its optical centre, its log blocks fitted by a 33-node
bilinear grid per channel; pooled node by node in the store, :mod:`vigproc.stores.profile_grid`),
compared the same way and applied as the profile's model corrects
(:meth:`vigproc.core.gridfield.GridFieldModel.correct_image`); the Kang-Weiss columns apply
the same profile's θ and colour field (:func:`vigproc.core.correct.correct`).

DNG part: vigproc's correction by the GainMap (:class:`vigproc.io.dng_vignette.GainFieldModel`)
against an independent implementation of the DNG specification's interpolation
(pixel centres at ((row + ½)/H, (col + ½)/W), bilinear, clamped), per channel; and the
per-plane GainMaps vigproc writes for the fitted model read back (the model's field
against the written maps'), in EV.
"""

from __future__ import annotations

import logging
import math
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from vigproc.core.colour_difference import ciede2000, linear_rgb_to_lab
from vigproc.core.model import VignettingModel, frame_coords

log = logging.getLogger(__name__)

WIDTH, HEIGHT = 480, 320
#: Half-diagonal of a 3:2 35-mm frame (mm).
HALF_DIAGONAL_35 = 21.633
#: Largest planar illumination gradient across the frame (natural log, edge to edge).
GRADIENT = 0.10
#: The wall's colour (a per-channel constant: white balance).
WALL = (0.9, 1.0, 0.8)
NOISE = 0.01
PATCH = 16
GREY = 0.18
_LN2 = math.log(2.0)
GAINMAP = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw" / "dng_opcodes" / "GainMap.bin"


@dataclass(frozen=True)
class ColourLens:
    """A true per-channel field: ln φ_c on the 480×320 frame (H×W×3)."""

    name: str
    log_fields: np.ndarray
    note: str = ""


def physical_field(focal35: float, k: Sequence[float], center: tuple[float, float] = (0.0, 0.0),
                   width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """ln T_c(θ) = k_c ln cos θ, θ = atan(r / f), H×W×3.

    ``focal35``: focal length in 35-mm terms (the frame's half-diagonal is
    :data:`HALF_DIAGONAL_35` mm); ``center``: optical centre, px from the frame's."""
    f_px = focal35 / HALF_DIAGONAL_35 * 0.5 * math.hypot(width, height)
    x = frame_coords(width)[None, :] - center[0]
    y = frame_coords(height)[:, None] - center[1]
    ln_cos = -0.5 * np.log1p((x * x + y * y) / (f_px * f_px))  # ln cos(atan(r/f))
    return np.stack([kc * ln_cos for kc in k], axis=-1)


def physical_fields() -> list[ColourLens]:
    """The physical settings (focal length in 35-mm terms, k_R, k_G, k_B)."""
    settings = [
        ("wide-24mm", 24.0, (3.6, 3.0, 2.6), (0.0, 0.0)),
        ("rangefinder-21mm", 21.0, (4.6, 3.4, 2.8), (0.0, 0.0)),
        ("phone-26mm", 26.0, (4.4, 3.2, 2.2), (0.0, 0.0)),
        ("phone-26mm-off-centre", 26.0, (4.4, 3.2, 2.2), (14.0, -9.0)),
        ("neutral-35mm", 35.0, (4.0, 4.0, 4.0), (0.0, 0.0)),
    ]
    return [ColourLens(n, physical_field(f, k, c), f"f={f:g}mm k={k} centre={c}") for n, f, k, c in settings]


def gainmap_fields(path: Path = GAINMAP) -> list[ColourLens]:
    """The real per-plane GainMap as a field (φ_c = 1/g_c); empty when the file is absent."""
    if not path.exists():
        log.warning("%s is absent: no real gain map in the colour bench", path)
        return []
    from vigproc.io.dng_opcodes import parse_opcode_list

    out = []
    for i, op in parse_opcode_list(path.read_bytes(), path.name).decoded():
        rv, rh = (np.arange(HEIGHT) + 0.5) / HEIGHT, (np.arange(WIDTH) + 0.5) / WIDTH
        lf = np.stack([-np.log(op.gain_grid(rv, rh, WIDTH, HEIGHT, c)) for c in range(3)], axis=-1)
        out.append(ColourLens(f"dng-gainmap-{i}", lf, f"{path.name} {op.points[0]}x{op.points[1]}x{op.map_planes}"))
    return out


def flat_frames(lens: ColourLens, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """``n`` flat frames of ``lens`` (see the module's protocol)."""
    h, w = lens.log_fields.shape[:2]
    xx = frame_coords(w)[None, :] / w
    yy = frame_coords(h)[:, None] / h
    out = []
    for _ in range(n):
        a = rng.uniform(0, 2 * math.pi)
        g = GRADIENT * rng.uniform(-1, 1)
        ramp = np.exp(g * (xx * math.cos(a) + yy * math.sin(a)))
        img = np.exp(lens.log_fields) * ramp[..., None] * np.array(WALL) * 0.5
        out.append(np.clip(img * (1 + NOISE * rng.standard_normal(img.shape)), 1e-6, None))
    return out


def learn_profile(frames: Sequence[np.ndarray]) -> tuple[VignettingModel, list[tuple[float, float]]]:
    """The flat frames' profile model, as ``vigproc profile learn --method flat-field``
    pools them (a temporary store: θ, colour field and each frame's grid field,
    :func:`vigproc.pipeline.flat_grid.frame_grid`), and each frame's optical centre as its
    estimate placed it (its tint's centre, else its fall-off's). The model is a
    :class:`vigproc.core.gridfield.GridFieldModel`: its ``grid`` is the store's pooled grid."""
    from vigproc.core.estimate import estimate
    from vigproc.pipeline.flat_grid import frame_grid
    from vigproc.stores.profiles import ProfileKey, ProfileStore, aspect_label

    h, w = frames[0].shape[:2]
    key = ProfileKey("bench|colour", "any", "any", aspect_label(w / h))
    with tempfile.TemporaryDirectory(prefix="vigproc-bench-") as tmp, \
            ProfileStore(Path(tmp) / "profiles.sqlite") as st:
        p = None
        centres = []
        for i, f in enumerate(frames):
            m = estimate(f, "flat-field")
            fit = m if m.candidate is None else replace(m.candidate, colour=m.colour)
            p = st.learn(key, fit, frame_id=f"shot{i}", grid=frame_grid(f, fit))
            centres.append(m.colour.center if m.colour is not None else fit.center)
        return p.model(w, h), centres


def channel_ev(log_ratio: np.ndarray) -> np.ndarray:
    """RMS over the frame of a per-channel natural-log ratio about its mean, EV (3,)."""
    d = log_ratio - log_ratio.mean(axis=(0, 1))
    return np.sqrt(np.mean(d * d, axis=(0, 1))) / _LN2


def corner_delta_e(gain_log: np.ndarray) -> tuple[float, float]:
    """Worst corner's CIEDE2000 against the centre for a grey patch seen through the
    per-channel attenuation ``gain_log`` (ln, H×W×3): (full ΔE00, ΔE00 with the
    corner's luminance equalised to the centre's)."""
    h, w = gain_log.shape[:2]
    grey = GREY * np.exp(gain_log)

    def patch(r: int, c: int) -> np.ndarray:
        return grey[r:r + PATCH, c:c + PATCH].reshape(-1, 3).mean(axis=0)

    centre = patch(h // 2 - PATCH // 2, w // 2 - PATCH // 2)
    lab_c = linear_rgb_to_lab(centre)
    luma = np.array([0.2126, 0.7152, 0.0722])
    full, tint = 0.0, 0.0
    for r, c in ((0, 0), (0, w - PATCH), (h - PATCH, 0), (h - PATCH, w - PATCH)):
        p = patch(r, c)
        full = max(full, float(ciede2000(lab_c, linear_rgb_to_lab(p))))
        tint = max(tint, float(ciede2000(lab_c, linear_rgb_to_lab(p * (centre @ luma) / (p @ luma)))))
    return full, tint


@dataclass
class FlatRow:
    """One field's figures."""

    name: str
    note: str
    truth_ev: list[float]  # per channel RMS of log2 φ_c about its mean (how strong)
    tint_ev: list[float]  # per channel RMS of log2 (φ_c / φ_G) about its mean (R, B; G 0)
    field_ev: list[float]  # per channel error of the fitted field, EV
    luminance_only_ev: list[float]  # the same for the luminance model alone (today's correction)
    bases_ev: list[float]  # per channel, median over the bases of the corrected frame's error
    de_uncorrected: tuple[float, float]
    de_luminance_only: tuple[float, float]
    de_corrected: tuple[float, float]
    colour_found: bool
    sigma_ev: float = math.nan
    grid_ev: list[float] = field(default_factory=list)  # the profile's pooled grid field's error, EV per channel
    grid_bases_ev: list[float] = field(default_factory=list)
    de_grid: tuple[float, float] = (math.nan, math.nan)
    extra: dict = field(default_factory=dict)


def run_flat(lenses: Sequence[ColourLens], bases: Sequence[np.ndarray], frames: int = 3,
             seed: int = 0) -> list[FlatRow]:
    """The flat part of the protocol (module docstring) for each of ``lenses``."""
    from vigproc.core.correct import correct

    rng = np.random.default_rng(seed)
    rows = []
    for lens in lenses:
        h, w = lens.log_fields.shape[:2]
        shots = flat_frames(lens, frames, rng)
        m, centres = learn_profile(shots)
        est_grid = m.grid.log_fields(w, h)  # the profile's pooled grid, as its correct_image divides
        est = m.channel_log_fields((h, w))  # its Kang-Weiss θ and colour field (correct() applies these)
        lum_only = VignettingModel(m.width, m.height, m.center, m.p, m.alpha)
        est_lum = lum_only.channel_log_fields((h, w))
        truth = lens.log_fields
        bases_err, grid_err = [], []

        def base_ev(out: np.ndarray, b: np.ndarray) -> np.ndarray:
            ok = np.all((b > 1e-3) & (out > 0), axis=2)
            lr = np.log(np.where(ok[..., None], out, 1.0) / np.where(ok[..., None], b, 1.0))
            d = lr[ok] - lr[ok].mean(axis=0)
            return np.sqrt(np.mean(d * d, axis=0)) / _LN2

        for b in bases:
            vig = b * np.exp(truth)
            bases_err.append(base_ev(correct(vig, m), b))
            grid_err.append(base_ev(m.correct_image(vig), b))
        rows.append(FlatRow(
            name=lens.name, note=lens.note,
            truth_ev=channel_ev(truth).tolist(),
            tint_ev=channel_ev(truth - truth[..., 1:2]).tolist(),
            field_ev=channel_ev(est - truth).tolist(),
            luminance_only_ev=channel_ev(est_lum - truth).tolist(),
            bases_ev=(np.median(bases_err, axis=0) if bases_err else np.full(3, math.nan)).tolist(),
            de_uncorrected=corner_delta_e(truth),
            de_luminance_only=corner_delta_e(truth - est_lum),
            de_corrected=corner_delta_e(truth - est),
            colour_found=m.colour is not None,
            sigma_ev=m.colour.sigma_ev() if m.colour is not None else math.nan,
            grid_ev=channel_ev(est_grid - truth).tolist(),
            grid_bases_ev=(np.median(grid_err, axis=0) if grid_err else np.full(3, math.nan)).tolist(),
            de_grid=corner_delta_e(truth - est_grid),
        ))
        log.info("%s: field error %s EV", lens.name, rows[-1].field_ev)
    return rows


@dataclass
class DngRow:
    name: str
    size: tuple[int, int]
    spec_rms_ev: list[float]
    spec_max_ev: list[float]
    written_max_ev: list[float]
    fit_rms_ev: float


def spec_gain(op, width: int, height: int, plane: int) -> np.ndarray:
    """The DNG specification's GainMap gain at every pixel of a width×height image,
    written independently of :meth:`GainMap.gain_grid` (scipy's bilinear
    ``map_coordinates`` on the clamped map index)."""
    from scipy.ndimage import map_coordinates

    pv, ph = op.points
    rv = np.clip(((np.arange(height) + 0.5) / height - op.origin_v) / op.spacing_v, 0, pv - 1)
    rh = np.clip(((np.arange(width) + 0.5) / width - op.origin_h) / op.spacing_h, 0, ph - 1)
    R, C = np.meshgrid(rv, rh, indexing="ij")
    return map_coordinates(op.gains[:, :, min(plane, op.map_planes - 1)].astype(np.float64), [R, C], order=1,
                           mode="nearest")


def run_dng(path: Path = GAINMAP, sizes: Sequence[tuple[int, int]] = ((480, 320), (1014, 760))) -> list[DngRow]:
    """The DNG part: vigproc's per-plane correction by the real GainMap against the
    spec's, and vigproc's written per-plane maps of the fitted model read back."""
    if not path.exists():
        log.warning("%s is absent: no DNG part", path)
        return []
    from vigproc.io.dng_opcodes import OpcodeList, parse_opcode_list
    from vigproc.io.dng_vignette import EmbeddedCalibration, model_to_gain_maps

    lst = parse_opcode_list(path.read_bytes(), path.name)
    (_, op), = lst.decoded()
    rows = []
    for w, h in sizes:
        cal = EmbeddedCalibration.from_lists([("OpcodeList3", lst)], path.name)
        m = cal.model(w, h)
        out = m.correct_image(np.ones((h, w, 3), dtype=np.float32))
        rms, mx = [], []
        for c in range(3):
            d = np.log2(out[..., c].astype(np.float64) / spec_gain(op, w, h, c))
            rms.append(float(np.sqrt(np.mean(d * d))))
            mx.append(float(np.abs(d).max()))
        # the model (Kang-Weiss fit + colour field) written as per-plane GainMaps, read back
        plain = VignettingModel(m.width, m.height, m.center, m.p, m.alpha, colour=m.colour)
        maps = model_to_gain_maps(plain)
        back = EmbeddedCalibration.from_lists([("OpcodeList3", OpcodeList(tuple(g.to_opcode() for g in maps)))], "w")
        want = -plain.channel_log_fields()
        wmax = [float(np.abs(back.log_gain(w, h, c) - want[..., c]).max() / _LN2) for c in range(3)]
        _, fit_rms = cal.colour(w, h, m.center)
        rows.append(DngRow(path.name, (w, h), rms, mx, wmax, fit_rms))
    return rows


def report_flat(rows: Sequence[FlatRow], dng: Sequence[DngRow], n_bases: int, frames: int) -> str:
    """The flat and DNG parts as a text table."""
    lines = [f"colour shading from {frames} flat frames per lens (480x320, gradient up to {GRADIENT:g} ln across, "
             f"{NOISE:.0%} noise), learned into a profile; {n_bases} vignetting-free bases",
             "EV columns: R G B, RMS over the frame about the channel's mean; dE00: worst corner vs centre "
             "(grey patch), full / luminance equalised",
             f"{'lens':<24}{'tint R,B':>12}{'field error':>22}{'luminance only':>22}{'bases':>22}"
             f"{'dE uncorr':>12}{'dE lum-only':>12}{'dE corr':>12}  colour"
             f"{'grid error':>22}{'grid bases':>22}{'dE grid':>12}"]

    def ev(v):
        return " ".join(f"{x:.4f}" for x in v)

    for r in rows:
        lines.append(f"{r.name:<24}{r.tint_ev[0]:>6.3f}{r.tint_ev[2]:>6.3f}{ev(r.field_ev):>22}"
                     f"{ev(r.luminance_only_ev):>22}{ev(r.bases_ev):>22}"
                     f"{r.de_uncorrected[0]:>6.2f}/{r.de_uncorrected[1]:<5.2f}"
                     f"{r.de_luminance_only[0]:>6.2f}/{r.de_luminance_only[1]:<5.2f}"
                     f"{r.de_corrected[0]:>6.2f}/{r.de_corrected[1]:<5.2f}  {'yes' if r.colour_found else 'no ':<6}"
                     f"{ev(r.grid_ev):>22}{ev(r.grid_bases_ev):>22}{r.de_grid[0]:>6.2f}/{r.de_grid[1]:<5.2f}")
    if dng:
        lines.append("DNG per-plane GainMap: vigproc's correction vs the spec's interpolation (RMS, max EV per "
                     "channel); the fitted model written as per-plane GainMaps, read back (max EV)")
        for d in dng:
            lines.append(f"  {d.name} at {d.size[0]}x{d.size[1]}: spec RMS {' '.join(f'{x:.1e}' for x in d.spec_rms_ev)}"
                         f" max {' '.join(f'{x:.1e}' for x in d.spec_max_ev)}; written max {ev(d.written_max_ev)}; "
                         f"colour fit {d.fit_rms_ev:.4f} EV")
    return "\n".join(lines)


def lamp_gradient(aside: float, out: float, wall: tuple[float, float] = (1.2, 0.8)) -> tuple[float, float]:
    """A wall patch of ``wall`` metres (the frame) lit by one point lamp ``aside`` metres to
    the side of its centre and ``out`` metres in front of it: irradiance cos(incidence)/d².
    Returns (the planar part's edge-to-edge change, ln; the non-planar part's RMS, EV): how
    far the protocol's planar ±5 % is from a real set-up."""
    x, y = np.meshgrid(np.linspace(-wall[0] / 2, wall[0] / 2, 240), np.linspace(-wall[1] / 2, wall[1] / 2, 160))
    d2 = (x - aside) ** 2 + y * y + out * out
    le = np.log(out / np.sqrt(d2) / d2).ravel()
    A = np.stack([np.ones(x.size), x.ravel(), y.ravel()], axis=1)
    c = np.linalg.lstsq(A, le, rcond=None)[0]
    r = le - A @ c
    return float(np.ptp(A[:, 1:] @ c[1:])), float(np.sqrt(np.mean(r * r)) / _LN2)


def lamp_table() -> str:
    """:func:`lamp_gradient` for a few single-lamp set-ups, as a text table."""
    rows = ["lamp aside, out (m)   planar edge-to-edge (ln)   non-planar RMS (EV)"]
    for a, o in ((1.5, 2.0), (0.5, 3.0), (3.0, 4.0), (6.0, 8.0)):
        p, n = lamp_gradient(a, o)
        rows.append(f"{a:>5.1f} {o:>5.1f}            {p:>8.3f}                  {n:.4f}")
    return "\n".join(rows)


def run_turned(lens: ColourLens | None = None, trials: int = 3, seed: int = 0) -> list[dict]:
    """The grid field from 3 flat frames (each frame's gradient removed about its optical
    centre, :func:`vigproc.core.gridfield.flat_grid`) against 2 pairs of frames shot with the
    camera turned 180° between a pair's frames (the wall's gradient turns with the frame,
    the lens's field does not: the pair's gradients cancel, nothing is removed), per
    channel EV error (default lens: the real GainMap). The optical centre is the first
    frame's flat-field estimate's."""
    from vigproc.core.estimate import estimate
    from vigproc.core.gridfield import flat_grid

    lens = lens or (gainmap_fields() or [None])[0]
    if lens is None:
        return []
    lf = lens.log_fields
    h, w = lf.shape[:2]
    rng = np.random.default_rng(seed)

    def shot(g: float, a: float) -> np.ndarray:
        ramp = np.exp(g * (frame_coords(w)[None, :] / w * math.cos(a) + frame_coords(h)[:, None] / h * math.sin(a)))
        img = np.exp(lf) * ramp[..., None] * np.array(WALL) * 0.5
        return np.clip(img * (1 + NOISE * rng.standard_normal(img.shape)), 1e-6, None)

    out = []
    for _ in range(trials):
        gs = [(GRADIENT * rng.uniform(-1, 1), rng.uniform(0, 2 * math.pi)) for _ in range(3)]
        three = [shot(g, a) for g, a in gs]
        turned = [shot(s * g, a) for g, a in gs[:2] for s in (1, -1)]
        m = estimate(three[0], "flat-field")
        c = m.colour.center if m.colour is not None else m.center
        out.append({"removed_3": channel_ev(flat_grid(three, [c] * 3).log_fields(w, h) - lf).tolist(),
                    "turned_2x2": channel_ev(flat_grid(turned, [c] * 4, remove_gradient=False).log_fields(w, h)
                                             - lf).tolist()})
    return out
