"""Removing vignetting: divide the linear image by the attenuation field.

The field is evaluated on the fly by a parallel Numba kernel
(:mod:`vigproc.core._kernels.correct`): no H×W field array is allocated, every channel
shares one gain computation, and a frame can be corrected in horizontal stripes
(:func:`correct_stripe`) so memory stays bounded for very large frames.
"""

from __future__ import annotations

import operator

import numpy as np

from vigproc.core._kernels.codes import correct_codes as correct_codes_rows
from vigproc.core._kernels.correct import correct_rows
from vigproc.core._kernels.field import log_field_grid
from vigproc.errors import InvalidImageError
from vigproc.core.pixels import as_channels_last
from vigproc.core.model import VignettingModel, blackout_error, frame_coords


#: Largest strength: 2 removes the fall-off twice over (the command line's bound too).
MAX_STRENGTH = 2.0


def _number(value: object, name: str) -> float:
    # bool is an int to Python, never a strength or a white point
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidImageError(f"{name} must be a number, got {value!r}")
    return float(value)


def _check_strength(strength: float) -> float:
    s = _number(strength, "strength")
    if not (np.isfinite(s) and 0.0 <= s <= MAX_STRENGTH):
        raise InvalidImageError(f"strength must be a number within [0, {MAX_STRENGTH:g}], got {strength!r}")
    return s


def _check_clip(clip: float | None) -> float:
    """The kernel's clip argument: a white point > 0, or −1 for none."""
    if clip is None:
        return -1.0
    c = _number(clip, "clip")
    if not (np.isfinite(c) and c > 0.0):
        raise InvalidImageError(f"clip must be None or a white point > 0, got {clip!r}")
    return c


def _min_g(m: VignettingModel, width: int, height: int, n: int = 4097) -> float:
    """Smallest G = 1 − Σ α_i r^i over a width×height frame.

    r² is a convex quadratic in the pixel position, so over the frame r runs from its
    minimum (0 when the centre is inside, else on an edge) to its largest corner
    value, and G is a polynomial in r: sampling that interval finely finds its
    minimum without evaluating the frame.
    """
    if m.is_identity:
        return 1.0
    p1, p2, p3 = m.p
    hx, hy = (width - 1) / 2.0, (height - 1) / 2.0
    cx, cy = m.center

    def q(ex, ey):
        return p1 * ex * ex + 2.0 * p2 * ex * ey + p3 * ey * ey

    xs, ys = np.array([-hx, hx]) - cx, np.array([-hy, hy]) - cy
    q_max = max(q(ex, ey) for ex in xs for ey in ys)
    if xs[0] <= 0.0 <= xs[1] and ys[0] <= 0.0 <= ys[1]:
        q_min = 0.0
    else:  # the minimum of a convex quadratic over the rectangle lies on an edge
        cands = []
        for ey in ys:
            ex = float(np.clip(-p2 * ey / p1, xs[0], xs[1])) if p1 > 0 else xs[0]
            cands.append(q(ex, ey))
        for ex in xs:
            ey = float(np.clip(-p2 * ex / p3, ys[0], ys[1])) if p3 > 0 else ys[0]
            cands.append(q(ex, ey))
        q_min = max(min(cands), 0.0)
    r = np.linspace(np.sqrt(q_min), np.sqrt(max(q_max, 0.0)), n)
    g = 1.0 - (r[:, None] ** np.arange(1, len(m.alpha) + 1)) @ np.asarray(m.alpha, dtype=np.float64)
    return float(g.min())


#: Relative error allowed from interpolating the gain between evaluated columns:
#: 1e-5 (1.4e-5 EV) is below a 16-bit output's quantisation step (1.5e-5 of full
#: scale, more relative to mid-tones) and far below anything visible.
GAIN_TOLERANCE = 1e-5
#: Largest interpolation step (columns).
MAX_GAIN_STEP = 16


def exact_radius(model: VignettingModel, step: int, tol: float = GAIN_TOLERANCE) -> float:
    """Radius (px) around the centre where gains must be evaluated exactly at ``step``.

    α1·r is a cone at the centre; near it r'' ≈ √λmax(P)/d at distance d, so linear
    interpolation over h columns errs by about |α1|·√λmax·h²/(8d) relative, which is
    within ``tol`` for d > |α1|·√λmax·h²/(8·tol).
    """
    if step <= 1:
        return 0.0
    lam = float(np.linalg.eigvalsh(model.shape_matrix).max())
    return abs(model.alpha[0]) * np.sqrt(max(lam, 0.0)) * step * step / (8 * tol) + step + 1.0


def gain_step(model: VignettingModel, width: int, height: int, tol: float = GAIN_TOLERANCE) -> int:
    """Column step at which linear interpolation of 1/φ stays within ``tol`` (relative).

    Linear interpolation over a step h errs by at most h²/8·max|g''|; the relative
    second difference of the exact gain g = 1/φ is measured along 9 rows spanning
    the frame (the corners, where it is largest, included), away from the centre's
    cone (:func:`exact_radius`), which is evaluated exactly.
    """
    m = model if (model.width, model.height) == (width, height) else model.rescale(width, height)
    if m.is_identity or width < 3:
        return MAX_GAIN_STEP if m.is_identity else 1
    rows = np.linspace(0, height - 1, 9).round().astype(int)
    g = np.exp(-_sample_rows(m, width, height, rows))
    curv = np.abs(g[:, 2:] - 2 * g[:, 1:-1] + g[:, :-2]) / g[:, 1:-1]
    xs = np.arange(1, width - 1) - ((width - 1) / 2 + m.center[0])
    ys = rows[:, None] - ((height - 1) / 2 + m.center[1])
    for step in range(MAX_GAIN_STEP, 1, -1):
        away = np.hypot(xs[None, :], ys) >= exact_radius(m, step, tol)
        if away.mean() < 0.9:  # the exact disc would cover much of the frame: no gain
            continue
        if step * step * float(curv[away].max()) / 8 <= tol:
            return step
    return 1


def _sample_rows(m: VignettingModel, width: int, height: int, rows: np.ndarray) -> np.ndarray:
    out = np.empty((rows.shape[0], width))
    ys = frame_coords(height)[rows]
    log_field_grid(frame_coords(width), ys, m.center[0], m.center[1], *m.p,
                   np.asarray(m.alpha, dtype=np.float64), out)
    return out


def _checked_model(model: VignettingModel, width: int, height: int) -> VignettingModel:
    """``model`` at ``width``×``height``; ModelError when its G reaches 0 in the frame."""
    m = model if (model.width, model.height) == (width, height) else model.rescale(width, height)
    gmin = _min_g(m, width, height)
    if gmin <= 0.0:  # what field() refuses; the kernel's floor would multiply by ~1e9
        raise blackout_error(gmin)
    return m


#: Rows per block when the colour ratios are applied (bounds the H×W×3 float64 temporaries).
COLOUR_ROWS = 256


def _apply_colour(o: np.ndarray, m: VignettingModel, row0: int, fh: int, fw: int, s: float, c: float) -> None:
    """Divide channels 0..2 of the luminance-corrected ``o`` (rows ``row0``.. of the
    frame) by their colour ratios ρ_c^s, in place, then clip at ``c`` (> 0)."""
    for i in range(0, o.shape[0], COLOUR_ROWS):
        rows = np.arange(row0 + i, row0 + min(i + COLOUR_ROWS, o.shape[0]))
        gain = np.exp(-s * m.colour.log_ratios(fw, fh, rows=rows)).astype(np.float32)
        blk = o[i:i + rows.size, :, :3]
        np.multiply(blk, gain, out=blk)
        if c > 0:  # every channel (an alpha too), as the kernel would have
            np.minimum(o[i:i + rows.size], np.float32(c), out=o[i:i + rows.size])


def correct_stripe(
    stripe: np.ndarray, model: VignettingModel, row0: int, frame_shape: tuple[int, int], *,
    strength: float = 1.0, clip: float | None = None, out: np.ndarray | None = None,
    step: int | None = None,
) -> np.ndarray:
    """Correct rows ``row0 .. row0 + h − 1`` of a frame of ``frame_shape`` = (H, W).

    Parameters
    ----------
    stripe : ndarray, h×W×C (channels last) or h×W
    model : VignettingModel
        Any resolution of the same frame; rescaled to (W, H) here.
    row0 : int
        Frame row of ``stripe[0]``.
    frame_shape : (H, W)
    strength, clip : see :func:`correct`
    out : ndarray, float32, same shape as ``stripe``, optional
        Destination (may be ``stripe`` itself when it is float32: in place).
    step : int, optional
        Gain interpolation step in columns (1 = exact); default :func:`gain_step`.

    Returns
    -------
    ndarray, float32
    """
    s = _check_strength(strength)
    c = _check_clip(clip)
    if not isinstance(model, VignettingModel):
        raise InvalidImageError(f"model must be a VignettingModel, got {type(model).__name__}")
    stripe = np.asarray(stripe)
    if stripe.dtype.kind not in "fiu":  # bool, complex, object and text are not intensities
        raise InvalidImageError(f"image must be real numbers, got dtype {stripe.dtype}")
    try:
        fh, fw = (operator.index(v) for v in frame_shape)
        row0 = operator.index(row0)
        step = None if step is None else operator.index(step)
    except (TypeError, ValueError):
        raise InvalidImageError(f"frame_shape must be two integers and row0, step integers; got "
                                f"{frame_shape!r}, {row0!r}, {step!r}") from None
    x = stripe[..., None] if stripe.ndim == 2 else stripe
    if x.ndim != 3 or x.shape[1] != fw or fh < 1 or not 0 <= row0 <= fh - x.shape[0]:
        raise InvalidImageError(f"stripe of shape {stripe.shape} at row {row0} does not fit a {fw}x{fh} frame")
    if step is not None and step < 1:
        raise InvalidImageError(f"step must be at least 1 column, got {step}")
    m = _checked_model(model, fw, fh)
    if out is None:
        out = np.empty(stripe.shape, dtype=np.float32)
    o = out[..., None] if out.ndim == 2 else out
    if o.shape != x.shape or o.dtype != np.float32:
        raise InvalidImageError(f"out must be float32 of shape {stripe.shape}, got {out.dtype} {out.shape}")
    if not o.flags.writeable:
        raise InvalidImageError("out is read-only")
    x = np.ascontiguousarray(x, dtype=np.float32)
    # The kernel writes row by row into C-ordered memory. ``out`` that is the input
    # itself (in place) is fine; any other layout, or memory overlapping the input
    # some other way, goes through a temporary so nothing is read after it is written.
    same = (o.__array_interface__["data"][0] == x.__array_interface__["data"][0]
            and o.strides == x.strides)
    direct = o.flags.c_contiguous and (same or not np.may_share_memory(o, x))
    dst = o if direct else np.empty(x.shape, dtype=np.float32)
    cy = (fh - 1) / 2.0 + m.center[1]
    step = gain_step(m, fw, fh) if step is None else step
    colour = m.colour is not None and s != 0.0 and x.shape[2] >= 3
    # with a colour field the white point clips after the channel's own gain, not before
    bad = correct_rows(x, dst, row0, m.center[0], cy, *m.p, np.asarray(m.alpha, dtype=np.float64),
                       s, -1.0 if colour else c, step, exact_radius(m, step))
    if not direct:
        o[...] = dst
    if colour:
        _apply_colour(o, m, row0, fh, fw, s, c)
        bad = bad or int(np.count_nonzero(~np.all(np.isfinite(o[..., :3]), axis=(1, 2))))
    if bad:
        raise InvalidImageError(f"the corrected image has NaN or Inf values in {bad} rows: the input holds "
                                "NaN/Inf, or its values are too large for float32 once corrected")
    return out


def correct(
    img: np.ndarray, model: VignettingModel, *, channel_axis: int | None = -1,
    strength: float = 1.0, clip: float | None = None, out: np.ndarray | None = None,
) -> np.ndarray:
    """Remove vignetting from a linear image: I = I_v / φ^strength (Lyu 2010, Eq. 1);
    with a colour field (``model.colour``) each of R, G, B by its own field,
    I_c = I_v,c / (φ·ρ_c)^strength (a 2-D frame, or fewer than 3 channels: φ alone).

    Parameters
    ----------
    img : ndarray
        H×W or H×W×C linear image (any resolution of the model's frame).
    model : VignettingModel
    channel_axis : int or None
    strength : float
        0 leaves the image unchanged, 1 removes the full fall-off.
    clip : float, optional
        Clip results above this white point (e.g. 1.0 for integer outputs); None
        keeps values above it (float outputs).
    out : ndarray, optional
        float32 destination of ``img``'s shape; pass ``img`` itself (float32,
        channels last) to correct in place.

    Returns
    -------
    ndarray, float32, same layout as ``img``

    Examples
    --------
    An evenly lit grey frame seen through a lens whose corners lose about half a stop:

    >>> import numpy as np
    >>> import vigproc
    >>> lens = vigproc.VignettingModel(240, 160, p=(1 / 150**2, 0.0, 1 / 150**2))
    >>> img = np.full((160, 240, 3), 0.5) * lens.field()[..., None]  # H×W×C, linear
    >>> round(float(img[0, 0, 0]), 3)  # a corner, darker
    0.331
    >>> out = vigproc.correct(img, lens)
    >>> out.shape, out.dtype, bool(np.allclose(out, 0.5, atol=1e-3))
    ((160, 240, 3), dtype('float32'), True)
    >>> half = vigproc.correct(img, lens, strength=0.5)  # half the fall-off (in stops) removed
    >>> round(float(half[0, 0, 0]), 3)
    0.407
    """
    a = np.asarray(img)
    if a.ndim == 2:
        channel_axis = None
    x = as_channels_last(a, channel_axis)
    h, w = x.shape[:2]
    if a.ndim == 3 and channel_axis not in (-1, 2) and out is not None:
        raise InvalidImageError("out= needs a channels-last image")
    res = correct_stripe(x, model, 0, (h, w), strength=strength, clip=clip, out=out)
    if a.ndim == 3 and channel_axis is not None and channel_axis not in (-1, 2):
        res = np.moveaxis(res, -1, channel_axis)
    return res


def _codes_colour(x: np.ndarray, out: np.ndarray, m: VignettingModel, lut: np.ndarray, st: np.ndarray,
                  s: float) -> None:
    """:func:`correct_codes` for a model with a colour field: per channel gains
    1/(φ·ρ_c)^s, block by block of rows (decode table, gains, then the code of each
    value found in ``st`` by binary search: the same round-half-up quantisation)."""
    fh, fw, ch = x.shape
    top = st.shape[0]
    for i in range(0, fh, COLOUR_ROWS):
        rows = np.arange(i, min(i + COLOUR_ROWS, fh))
        lg = -s * _sample_rows(m, fw, fh, rows)  # ln of the luminance gain
        gain = np.empty((rows.size, fw, ch), dtype=np.float32)
        gain[...] = np.exp(lg)[..., None]
        gain[..., :3] *= np.exp(-s * m.colour.log_ratios(fw, fh, rows=rows))
        codes = np.searchsorted(st, lut[x[rows[0]:rows[-1] + 1]] * gain, side="right")
        out[rows[0]:rows[-1] + 1] = np.minimum(codes, top)


#: Cells of [0, 1) in which :func:`correct_codes` looks up where an output code's search
#: starts: 8-bit codes step at least 3e-4 apart in linear light, wider than a cell
#: (1.5e-5), so the lookup is off by at most one step there.
ENCODE_CELLS = 65536


def correct_codes(codes: np.ndarray, model: VignettingModel, decode: np.ndarray, steps: np.ndarray, *,
                  strength: float = 1.0, out: np.ndarray | None = None) -> np.ndarray:
    """Correct a display-encoded frame in its own domain: each code value decoded by the
    table ``decode``, multiplied by the gain 1/φ^strength, and encoded back by
    ``steps`` (what :func:`correct` then an encode with round-half-up quantisation give,
    without a float frame or a float power over every sample).

    Parameters
    ----------
    codes : ndarray, H×W or H×W×C, uint8 or uint16
        The frame's code values.
    model : VignettingModel
        Any resolution of the same frame.
    decode : ndarray, float32
        Linear value of every code (``decode[codes]`` is the linear frame).
    steps : ndarray, float32, sorted
        ``steps[c]``: the linear value from which the output code is ``c + 1``; its
        length is the output's top code (255, 65535), which values above the white point
        are clipped to.
    strength : float
        As :func:`correct`.
    out : ndarray, optional
        Where to write the result: C-contiguous, the shape of ``codes`` and the output's
        dtype; may be ``codes`` itself (each sample is read before it is written), which
        spares a second frame in memory.

    Returns
    -------
    ndarray, the shape of ``codes``, uint8 when ``steps`` has at most 255 entries, else uint16
    """
    s = _check_strength(strength)
    if not isinstance(model, VignettingModel):
        raise InvalidImageError(f"model must be a VignettingModel, got {type(model).__name__}")
    a = np.asarray(codes)
    if a.dtype not in (np.uint8, np.uint16) or a.ndim not in (2, 3):
        raise InvalidImageError(f"codes must be an H×W(×C) uint8 or uint16 array, got {a.dtype} {a.shape}")
    lut = np.ascontiguousarray(decode, dtype=np.float32)
    if lut.ndim != 1 or lut.shape[0] < int(a.max()) + 1:
        raise InvalidImageError(f"the decode table has {lut.shape[0]} entries for codes up to {int(a.max())}")
    st = np.ascontiguousarray(steps, dtype=np.float32)
    x = np.ascontiguousarray(a[..., None] if a.ndim == 2 else a)
    fh, fw = x.shape[:2]
    m = _checked_model(model, fw, fh)
    dtype = np.uint8 if st.shape[0] <= 255 else np.uint16
    if out is None:
        out = np.empty(x.shape, dtype=dtype)
    else:
        if out.shape != a.shape or out.dtype != dtype or not out.flags.c_contiguous or not out.flags.writeable:
            raise InvalidImageError(f"out must be a writable C-contiguous {np.dtype(dtype)} array of shape {a.shape}, "
                                    f"got {out.dtype} {out.shape}")
        if a.ndim == 2:
            out = out[..., None]
        if np.shares_memory(out, x) and out.__array_interface__["data"][0] != x.__array_interface__["data"][0]:
            raise InvalidImageError("out overlaps codes without being codes itself")
    if m.colour is not None and x.shape[2] >= 3 and s != 0.0:
        _codes_colour(x, out, m, lut, st, s)  # block by block of rows: in place is safe
        return out[..., 0] if a.ndim == 2 else out
    step = gain_step(m, fw, fh)
    # where each code's search starts: the steps below each of 65536 cells of [0, 1)
    start = np.searchsorted(st, np.arange(ENCODE_CELLS) / ENCODE_CELLS, side="left").astype(np.int32)
    correct_codes_rows(x, out, lut, st, start, 0, m.center[0], (fh - 1) / 2.0 + m.center[1], *m.p,
                       np.asarray(m.alpha, dtype=np.float64), s, step, exact_radius(m, step))
    return out[..., 0] if a.ndim == 2 else out
