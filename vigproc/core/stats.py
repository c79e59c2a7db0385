"""Spatial means of the discrete derivative operators of Lyu 2010, Section 3.1.

Operators (step Δ, x = column to the right, y = row down; means are taken over the
pixels where the operator is defined, i.e. a "valid" convolution):

    D^x_Δ  i = i(x+Δ, y) − i(x, y)
    D^y_Δ  i = i(x, y+Δ) − i(x, y)
    D^xx_Δ i = i(x+Δ, y) − 2 i(x, y) + i(x−Δ, y)
    D^yy_Δ i = i(x, y+Δ) − 2 i(x, y) + i(x, y−Δ)
    D^xy_Δ i = i(x+Δ, y+Δ) − i(x+Δ, y) − i(x, y+Δ) + i(x, y)

The sums telescope, so every mean depends only on pixels within 2Δ of the borders:

    Σ D^x_Δ  = Σ_{k<Δ} (C_R[k] − C_L[k])
    Σ D^xx_Δ = Σ_{k<Δ} (C_R[k] + C_L[k]) − Σ_{Δ≤k<2Δ} (C_R[k] + C_L[k])
    Σ D^xy_Δ = K_tl(Δ) − K_tr(Δ) − K_bl(Δ) + K_br(Δ)

with C_L[k] / C_R[k] the sum of the k-th column from the left / right border, and
K_··(Δ) the sum of the Δ×Δ block in each corner (rows likewise for y, yy). All means
for Δ = 1..Δmax therefore cost O((H+W)·Δmax) and, for a parametric field, only need
the field on the border strips.

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010, Section 3.1, Eq. (5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vigproc.errors import InvalidImageError

#: Operator order used for every (operator, Δ) array in vigproc.
OPERATORS = ("x", "y", "xx", "yy", "xy")
#: Largest step used by Lyu 2010 (Δ = 1..25).
DELTA_MAX = 25


@dataclass(frozen=True)
class BorderSums:
    """Everything the telescoped derivative means need from an H×W field.

    ``col_l[k]``/``col_r[k]``: sum of the k-th column from the left/right border
    (k < 2Δmax); ``row_t``/``row_b`` likewise for rows; ``tl, tr, bl, br``: 2-D
    prefix sums ((Δmax+1)×(Δmax+1)) of the corner blocks, indexed [rows, cols]
    counted from that corner.
    """

    height: int
    width: int
    col_l: np.ndarray
    col_r: np.ndarray
    row_t: np.ndarray
    row_b: np.ndarray
    tl: np.ndarray
    tr: np.ndarray
    bl: np.ndarray
    br: np.ndarray


def _corner_prefix(block: np.ndarray) -> np.ndarray:
    out = np.zeros((block.shape[0] + 1, block.shape[1] + 1))
    out[1:, 1:] = np.cumsum(np.cumsum(block, axis=0), axis=1)
    return out


def check_size(height: int, width: int, delta_max: int) -> None:
    """Raise :class:`InvalidImageError` if an H×W image is too small for Δmax."""
    need = 2 * delta_max + 1
    if height < need or width < need:
        raise InvalidImageError(
            f"image of {width}x{height} px is too small for derivative steps up to "
            f"{delta_max}: need at least {need}x{need} px"
        )


def border_sums_from_strips(
    left: np.ndarray, right: np.ndarray, top: np.ndarray, bottom: np.ndarray,
    height: int, width: int, delta_max: int,
) -> BorderSums:
    """Build :class:`BorderSums` from the four border strips of a field.

    Parameters
    ----------
    left, right : ndarray, H×K
        The K = 2Δmax columns nearest the left/right border, each ordered from the
        border inwards (``right`` is mirrored).
    top, bottom : ndarray, K×W
        The K rows nearest the top/bottom border, ordered from the border inwards.
    """
    d = delta_max
    return BorderSums(
        height=height,
        width=width,
        col_l=left.sum(axis=0),
        col_r=right.sum(axis=0),
        row_t=top.sum(axis=1),
        row_b=bottom.sum(axis=1),
        tl=_corner_prefix(top[:d, :d]),
        tr=_corner_prefix(top[:d, ::-1][:, :d]),
        bl=_corner_prefix(bottom[:d, :d]),
        br=_corner_prefix(bottom[:d, ::-1][:, :d]),
    )


def border_sums(img: np.ndarray, delta_max: int = DELTA_MAX) -> BorderSums:
    """:class:`BorderSums` of a 2-D array (e.g. a log image)."""
    img = np.asarray(img, dtype=np.float64)
    if img.ndim != 2:
        raise InvalidImageError(f"expected a 2-D array, got shape {img.shape}")
    h, w = img.shape
    check_size(h, w, delta_max)
    k = 2 * delta_max
    return border_sums_from_strips(
        img[:, :k], img[:, w - k :][:, ::-1], img[:k, :], img[h - k :, :][::-1, :], h, w, delta_max
    )


def derivative_means_from_sums(bs: BorderSums, delta_max: int = DELTA_MAX) -> np.ndarray:
    """Spatial means of the five operators for Δ = 1..Δmax.

    Returns
    -------
    ndarray, shape (5, Δmax)
        Rows in :data:`OPERATORS` order, column Δ−1 for step Δ.
    """
    h, w, d = bs.height, bs.width, delta_max
    cl, cr, rt, rb = (np.concatenate([[0.0], np.cumsum(a)]) for a in (bs.col_l, bs.col_r, bs.row_t, bs.row_b))
    deltas = np.arange(1, d + 1)
    out = np.empty((5, d))
    # Σ_{k<Δ} via prefix sums; Σ_{Δ≤k<2Δ} = S[2Δ] − S[Δ]
    out[0] = (cr[deltas] - cl[deltas]) / (h * (w - deltas))
    out[1] = (rb[deltas] - rt[deltas]) / (w * (h - deltas))
    near_x = cr[deltas] + cl[deltas]
    far_x = (cr[2 * deltas] - cr[deltas]) + (cl[2 * deltas] - cl[deltas])
    out[2] = (near_x - far_x) / (h * (w - 2 * deltas))
    near_y = rb[deltas] + rt[deltas]
    far_y = (rb[2 * deltas] - rb[deltas]) + (rt[2 * deltas] - rt[deltas])
    out[3] = (near_y - far_y) / (w * (h - 2 * deltas))
    corners = bs.tl[deltas, deltas] - bs.tr[deltas, deltas] - bs.bl[deltas, deltas] + bs.br[deltas, deltas]
    out[4] = corners / ((w - deltas) * (h - deltas))
    return out


def derivative_means(img: np.ndarray, delta_max: int = DELTA_MAX) -> np.ndarray:
    """Exact spatial means of D^t_Δ img, t ∈ :data:`OPERATORS`, Δ = 1..Δmax.

    Parameters
    ----------
    img : ndarray, H×W
        Typically a log-intensity image i_v = log I_v.
    delta_max : int

    Returns
    -------
    ndarray, shape (5, Δmax)

    References
    ----------
    Lyu 2010, Section 3.1 and Eq. (5); computed in O((H+W)·Δmax) by telescoping.
    """
    return derivative_means_from_sums(border_sums(img, delta_max), delta_max)


def derivative_means_bruteforce(img: np.ndarray, delta_max: int = DELTA_MAX) -> np.ndarray:
    """Reference implementation by explicit valid-region differences (slow; for tests)."""
    i = np.asarray(img, dtype=np.float64)
    h, w = i.shape
    check_size(h, w, delta_max)
    out = np.empty((5, delta_max))
    for d in range(1, delta_max + 1):
        out[0, d - 1] = np.mean(i[:, d:] - i[:, :-d])
        out[1, d - 1] = np.mean(i[d:, :] - i[:-d, :])
        out[2, d - 1] = np.mean(i[:, 2 * d :] - 2 * i[:, d : w - d] + i[:, : w - 2 * d])
        out[3, d - 1] = np.mean(i[2 * d :, :] - 2 * i[d : h - d, :] + i[: h - 2 * d, :])
        out[4, d - 1] = np.mean(i[d:, d:] - i[d:, :-d] - i[:-d, d:] + i[:-d, :-d])
    return out
