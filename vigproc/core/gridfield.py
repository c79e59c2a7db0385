"""A lens's per-channel fall-off as a smooth grid, measured from flat frames.

A flat frame measures the field itself, so a profile learned from flat frames needs no
parametric model: the Kang-Weiss polynomial (:mod:`vigproc.core.model`) and the even
colour field (:mod:`vigproc.core.colour`) cannot hold every real lens (an IMX477 phone
module's measured gain map misses the best Kang-Weiss fit of its mean by 0.015 EV RMS,
0.16 EV in the corners; ``vigproc bench colour``). :class:`GridField` holds ln φ_c per
channel on a low-resolution grid of nodes spanning the frame, evaluated bilinearly as a
DNG ``GainMap`` is, with a 1-σ uncertainty per node.

What a flat frame cannot tell
-----------------------------
An unevenly lit wall adds a planar gradient to ln L in every channel alike. A grid holds
any plane, so the gradient must be removed first, about the optical centre (the tint's
centre, or the fall-off's centre of symmetry: :func:`vigproc.core.colour.planar_gradient`);
what remains in the grid of a lens's own linear tilt of luminance is lost with it (a
tilt of the tint, R/G or B/G, is kept: the wall's light is one colour). A per-channel
constant is white balance: only ratios across the frame matter.

References
----------
Adobe, *Digital Negative (DNG) Specification* 1.4.0.0, "GainMap" (node placement and
bilinear interpolation). Y. Zheng et al., "Single-image vignetting correction from
gradient distribution symmetries", IEEE TPAMI 35(6), 2013 (flat-field calibration).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from vigproc.core.colour import LUMA, planar_gradient
from vigproc.core.fieldjson import check_field_dict, field_to_dict
from vigproc.core.model import VignettingModel
from vigproc.core.pixels import as_channels_last, finish_corrected, luminance
from vigproc.errors import InvalidImageError, ModelError

SCHEMA = "vigproc.grid/1"
#: Default nodes on the long side (the short side in proportion): a least-squares grid
#: holds an IMX477 gain map (32×32 nodes) to 0.0019 EV RMS with 33 nodes over 480×320,
#: 0.0050 with 17 (the benchmark's truth, no noise).
NODES = 33
#: Weight of the second-difference smoothness penalty, relative to the data's mean
#: weight per node: it only decides nodes the blocks barely reach.
SMOOTH = 0.05
_LN2 = math.log(2.0)


def _nodes(n: int, size: int) -> np.ndarray:
    """Node positions in relative frame coordinates (0 and 1 at the frame's edges)."""
    return np.linspace(0.0, 1.0, n)


def _hat(t: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear weights of relative positions ``t`` on ``n`` equally spaced nodes:
    (left index, right index, right weight)."""
    u = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0) * (n - 1)
    i0 = np.minimum(np.floor(u).astype(int), n - 2) if n > 1 else np.zeros(u.shape, int)
    return i0, np.minimum(i0 + 1, n - 1), u - i0


def bilinear(nodes: np.ndarray, rv: np.ndarray, rh: np.ndarray) -> np.ndarray:
    """Values on ny×nx×C nodes spanning the frame (0 and 1 at its edges) at relative
    positions: rows ``rv`` down, columns ``rh`` across; len(rv)×len(rh)×C.

    Parameters
    ----------
    nodes : ndarray (ny, nx, C)
    rv, rh : ndarray
        Relative positions, clamped to 0..1.

    Returns
    -------
    ndarray
    """
    g = np.asarray(nodes, dtype=np.float64)
    ny, nx = g.shape[:2]
    j0, j1, fy = _hat(np.asarray(rv, dtype=np.float64), ny)
    i0, i1, fx = _hat(np.asarray(rh, dtype=np.float64), nx)
    top = g[j0][:, i0] * (1 - fx)[None, :, None] + g[j0][:, i1] * fx[None, :, None]
    bot = g[j1][:, i0] * (1 - fx)[None, :, None] + g[j1][:, i1] * fx[None, :, None]
    return top * (1 - fy)[:, None, None] + bot * fy[:, None, None]


@dataclass(frozen=True, eq=False)
class GridField:
    """ln φ_c on a grid of nodes spanning the frame (corner nodes on the frame's edges).

    Attributes
    ----------
    width, height : int
        The frame it was measured on (any resolution of it can be evaluated).
    log_field : ndarray (ny, nx, 3)
        ln φ_c at the nodes, R, G, B; relative (a per-channel constant is white balance).
    sigma : ndarray (ny, nx, 3) or None
        1-σ uncertainty of each node's value.
    source : str
    """

    width: int
    height: int
    log_field: Any
    sigma: Any = None
    source: str = ""

    def __post_init__(self) -> None:
        for k in ("width", "height"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ModelError(f"grid field {k} must be a positive integer, got {v!r}")
            object.__setattr__(self, k, int(v))
        try:
            lf = np.array(self.log_field, dtype=np.float64)
        except (TypeError, ValueError):
            raise ModelError("grid field log_field must be numbers") from None
        if lf.ndim != 3 or lf.shape[2] != 3 or min(lf.shape[:2]) < 2 or not np.all(np.isfinite(lf)):
            raise ModelError(f"grid field log_field must be finite ny×nx×3 with ny, nx >= 2, got {lf.shape}")
        if float(np.ptp(lf)) > 12 * _LN2:  # beyond 12 EV across the frame: a corrupt file, not a lens
            raise ModelError("grid field spans more than 12 EV: not a lens's fall-off")
        lf.setflags(write=False)
        object.__setattr__(self, "log_field", lf)
        if self.sigma is not None:
            s = np.array(self.sigma, dtype=np.float64)
            if s.shape != lf.shape or not np.all(np.isfinite(s)) or np.any(s < 0):
                raise ModelError("grid field sigma must be finite, >= 0, of log_field's shape")
            s.setflags(write=False)
            object.__setattr__(self, "sigma", s)
        object.__setattr__(self, "source", str(self.source))

    @property
    def nodes(self) -> tuple[int, int]:
        """(nx, ny)."""
        return (self.log_field.shape[1], self.log_field.shape[0])

    def log_fields(self, width: int | None = None, height: int | None = None,
                   rows: np.ndarray | None = None) -> np.ndarray:
        """ln φ_c at the pixel centres ((col + ½)/W, (row + ½)/H) of a ``width``×``height``
        resolution of the frame (default its own), H×W×3 (``rows``: only these)."""
        w = self.width if width is None else int(width)
        h = self.height if height is None else int(height)
        rv = (np.arange(h) + 0.5) / h if rows is None else (np.asarray(rows) + 0.5) / h
        return self.log_fields_rel(rv, (np.arange(w) + 0.5) / w)

    def log_fields_rel(self, rv: np.ndarray, rh: np.ndarray) -> np.ndarray:
        """ln φ_c at relative frame positions: rows ``rv`` down, columns ``rh`` across
        (0 and 1 at the frame's edges), len(rv)×len(rh)×3, bilinear as a DNG GainMap."""
        return bilinear(self.log_field, rv, rh)

    def centred(self, center: tuple[float, float]) -> GridField:
        """The same field with every channel 0 at ``center`` (px from the frame centre):
        a correction by it leaves that point as it is, as a Kang-Weiss model with a colour
        field leaves its optical centre (a per-channel constant is white balance)."""
        at = self.log_fields_rel(np.array([center[1] / self.height + 0.5]),
                                 np.array([center[0] / self.width + 0.5]))[0, 0]
        return GridField(self.width, self.height, self.log_field - at, self.sigma, self.source)

    def to_dict(self) -> dict[str, Any]:
        return field_to_dict(SCHEMA, self.width, self.height,
                             {"channels": ["R", "G", "B"], "log_field": self.log_field.tolist()},
                             self.sigma, self.source)

    @classmethod
    def from_dict(cls, d: Any) -> GridField:
        """The field of a :meth:`to_dict` mapping.

        Raises
        ------
        ModelError
            Unknown schema, missing or malformed fields.
        """
        sigma, source = check_field_dict(d, "grid field", SCHEMA, ("width", "height", "log_field"))
        return cls(d["width"], d["height"], d["log_field"], sigma, source)


def fit_grid(log_values: np.ndarray, rx: np.ndarray, ry: np.ndarray, nx: int, ny: int, width: int, height: int,
             *, smooth: float = SMOOTH, source: str = "") -> GridField:
    """The grid whose bilinear surface best fits log values per channel (least squares,
    a second-difference penalty for nodes few points reach).

    Parameters
    ----------
    log_values : ndarray (n, 3)
    rx, ry : ndarray (n,)
        The points' relative frame positions (0..1).
    nx, ny : int
        Nodes across and down (≥ 2).
    width, height : int
        The frame's size.

    Returns
    -------
    GridField
        Each channel's mean removed (white balance); σ per node from the residual.
    """
    v = np.asarray(log_values, dtype=np.float64).reshape(-1, 3)
    n = nx * ny
    j0, j1, fy = _hat(ry, ny)
    i0, i1, fx = _hat(rx, nx)
    A = np.zeros((v.shape[0], n))
    rows = np.arange(v.shape[0])
    for jj, wy in ((j0, 1 - fy), (j1, fy)):
        for ii, wx in ((i0, 1 - fx), (i1, fx)):
            np.add.at(A, (rows, jj * nx + ii), wy * wx)
    # second differences along x and y: a smooth surface where the data say little
    D = []
    for j in range(ny):
        for i in range(1, nx - 1):
            r = np.zeros(n)
            r[j * nx + i - 1], r[j * nx + i], r[j * nx + i + 1] = 1.0, -2.0, 1.0
            D.append(r)
    for j in range(1, ny - 1):
        for i in range(nx):
            r = np.zeros(n)
            r[(j - 1) * nx + i], r[j * nx + i], r[(j + 1) * nx + i] = 1.0, -2.0, 1.0
            D.append(r)
    Dm = np.array(D) if D else np.zeros((0, n))
    ata = A.T @ A
    lam = smooth * float(np.trace(ata)) / n
    M = ata + lam * (Dm.T @ Dm)
    try:
        Minv = np.linalg.inv(M)
    except np.linalg.LinAlgError:
        raise InvalidImageError("too few usable blocks for a grid field") from None
    sol = Minv @ (A.T @ v)
    res = v - A @ sol
    s2 = np.sum(res * res, axis=0) / max(v.shape[0] - n, 1)
    var = np.diag(Minv @ ata @ Minv)[:, None] * s2[None, :]
    lf = sol - sol.mean(axis=0)
    return GridField(width, height, lf.reshape(ny, nx, 3), np.sqrt(var).reshape(ny, nx, 3), source)


def flat_grid(frames: Sequence[np.ndarray], centers: Sequence[tuple[float, float]], *, nodes: int = NODES,
              block: int | None = None, remove_gradient: bool = True, source: str = "flat-field:grid") -> GridField:
    """The grid field of flat frames of one lens setting: each frame white-balanced
    (:func:`vigproc.core.colour.white_balance` where it has a colour field, else its
    channels' ratios at the centre), its wall's planar gradient removed about its optical
    centre (:func:`vigproc.core.colour.planar_gradient`), its log block means averaged
    over the frames and fitted by :func:`fit_grid`.

    Parameters
    ----------
    frames : sequence of H×W×3 linear frames of one size
    centers : sequence of (float, float)
        Each frame's optical centre, px from the frame centre (the tint's, or the
        fall-off's centre of symmetry: the flat-field estimate's ``colour.center`` or
        ``center``).
    nodes : int
        Nodes on the long side.
    block : int, optional
        Block size (default about 64 blocks on the long side).
    remove_gradient : bool
        Remove each frame's planar gradient about its centre (default). False: the
        frames' gradients are left to cancel in the average -- exactly for frames shot in
        pairs with the camera turned 180° between them (the wall's gradient turns with
        the frame, the lens's field does not), which keeps a lens's own tilt.

    Returns
    -------
    GridField

    Raises
    ------
    InvalidImageError
        Frames of different sizes or not H×W×3.
    """
    frames = list(frames)
    shapes = {np.shape(f) for f in frames}
    if len(shapes) != 1 or len(next(iter(shapes))) != 3 or next(iter(shapes))[2] < 3:
        raise InvalidImageError(f"a grid field needs flat frames of one H×W×3 size, got {sorted(shapes)}")
    h, w = frames[0].shape[:2]
    k = block or max(1, max(h, w) // 64)
    hb, wb = h // k, w // k
    xs = (np.arange(wb) * k + (k - 1) / 2.0) - (w - 1) / 2.0
    ys = (np.arange(hb) * k + (k - 1) / 2.0) - (h - 1) / 2.0
    X, Y = np.meshgrid(xs, ys)
    acc = np.zeros((hb, wb, 3))
    ok = np.ones((hb, wb), dtype=bool)
    for f, c in zip(frames, centers):
        a = np.asarray(f, dtype=np.float64)[..., :3]
        g = planar_gradient(luminance(a), c) if remove_gradient else np.zeros(2)
        m = a[: hb * k, : wb * k].reshape(hb, k, wb, k, 3).mean(axis=(1, 3))
        good = np.all(m > 0, axis=2)
        ok &= good
        lm = np.log(np.where(good[..., None], m, 1.0)) - (g[0] * X + g[1] * Y)[..., None]
        acc += lm - np.median(lm[good], axis=0)  # each frame's own white balance and level
    acc /= len(frames)
    ny = max(2, round(nodes * min(h, w) / max(h, w))) if w >= h else nodes
    nx = nodes if w >= h else max(2, round(nodes * w / h))
    return fit_grid(acc[ok], (X[ok] + (w - 1) / 2.0 + 0.5) / w, (Y[ok] + (h - 1) / 2.0 + 0.5) / h, nx, ny, w, h,
                    source=source)


def correct_with_grid(img: np.ndarray, grid: GridField, *, strength: float = 1.0) -> np.ndarray:
    """``img`` (H×W×3 linear, any resolution of the grid's frame) divided by the grid's
    per-channel field (``strength`` as its exponent), float32, one channel at a time.

    Raises
    ------
    InvalidImageError
        Not H×W×3, or the result is not finite.
    """
    a = np.asarray(img)
    if a.ndim != 3 or a.shape[2] < 3:
        raise InvalidImageError(f"a grid field corrects H×W×3 frames, got shape {a.shape}")
    h, w = a.shape[:2]
    lf = grid.log_fields(w, h)
    out = np.asarray(a, dtype=np.float32).copy()
    for c in range(3):
        np.multiply(out[..., c], np.exp(-float(strength) * lf[..., c]), out=out[..., c], casting="unsafe")
    if not np.all(np.isfinite(out)):
        raise InvalidImageError("the corrected image has NaN or Inf values")
    return out


@dataclass(frozen=True)
class GridFieldModel(VignettingModel):
    """A profile's measured grid field as a model: Kang-Weiss parameters (the profile's
    θ and colour field, for records, pictures, lensfun export and comparisons) and the
    grid itself (for correcting), as :class:`vigproc.io.dng_vignette.GainFieldModel`
    holds a DNG's maps.

    :meth:`correct_image` divides each of R, G, B by its own grid field; everything
    else sees an ordinary :class:`VignettingModel`.

    Attributes
    ----------
    grid : GridField or None
        ln φ_c of the frame (any resolution of it is corrected at its pixel centres).
    """

    grid: GridField | None = field(default=None, repr=False, compare=False)

    def correct_image(self, img: np.ndarray, *, channel_axis: int | None = -1, strength: float = 1.0,
                      clip: float | None = None) -> np.ndarray:
        """``img / φ_c^strength`` with φ_c the grid's field per channel (float32, ``img``'s
        layout); a grey frame (or fewer than 3 channels) by the luminance of the
        channels' fields (Rec. 709 weights, in log); channels after the third (alpha) too.

        Without a grid: :func:`vigproc.core.correct.correct` of the Kang-Weiss model.

        Raises
        ------
        InvalidImageError
            Bad strength or layout, or the result is not finite.
        """
        from vigproc.core.correct import _check_clip, _check_strength, correct  # Numba kernels: only when used

        if self.grid is None:
            return correct(img, self, channel_axis=channel_axis, strength=strength, clip=clip)
        s = _check_strength(strength)
        c = _check_clip(clip)
        a = np.asarray(img)
        if a.dtype.kind not in "fiu":
            raise InvalidImageError(f"image must be real numbers, got dtype {a.dtype}")
        x = as_channels_last(a, None if a.ndim == 2 else channel_axis)
        x = x[..., None] if x.ndim == 2 else x
        h, w, ch = x.shape
        out = np.empty(x.shape, dtype=np.float32)
        g = self.grid.log_field
        ny, nx = g.shape[:2]
        # separable: the node rows interpolated across the image's columns once (ny×W), then
        # each image row between its two node rows; float32 (a gain's rounding: 1e-7)
        i0, i1, fx = _hat((np.arange(w) + 0.5) / w, nx)
        across = (g[:, i0] * (1 - fx)[None, :, None] + g[:, i1] * fx[None, :, None]) * -s
        across = np.concatenate([across, (across @ LUMA)[..., None]], axis=2).astype(np.float32)
        j0, j1, fy = _hat((np.arange(h) + 0.5) / h, ny)
        fy = fy.astype(np.float32)
        band = max(1, (1 << 19) // max(w, 1))  # about half a million pixels at a time
        for r0 in range(0, h, band):
            r1 = min(h, r0 + band)
            t = fy[r0:r1, None, None]
            gain = across[j0[r0:r1]] * (1 - t) + across[j1[r0:r1]] * t  # rows×W×4: R, G, B, luminance
            np.exp(gain, out=gain)
            for k in range(ch):
                np.multiply(x[r0:r1, :, k], gain[..., k if ch >= 3 and k < 3 else 3], out=out[r0:r1, :, k],
                            casting="unsafe")
        return finish_corrected(out, a.ndim, c, channel_axis)
