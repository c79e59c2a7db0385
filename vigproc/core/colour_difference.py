"""CIELAB and the CIEDE2000 colour difference, for judging colour casts.

A cast is judged on a mid grey: the grey seen through the frame's centre and through
its corner, converted from linear sRGB (D65) to CIELAB, and compared with CIEDE2000.

References
----------
G. Sharma, W. Wu, E. N. Dalal, "The CIEDE2000 color-difference formula: implementation
notes, supplementary test data, and mathematical observations", Color Research and
Application 30(1), 2005.
IEC 61966-2-1 (sRGB primaries and D65 white).
"""

from __future__ import annotations

import numpy as np

#: linear sRGB → CIE XYZ (D65), IEC 61966-2-1
_RGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805],
                        [0.2126, 0.7152, 0.0722],
                        [0.0193, 0.1192, 0.9505]])
_WHITE = _RGB_TO_XYZ.sum(axis=1)
#: the mid grey a cast is judged on (linear; L* ≈ 50)
MID_GREY = 0.1842


def linear_rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """CIELAB (D65) of linear sRGB values.

    Parameters
    ----------
    rgb : array_like
        ``...×3`` linear R, G, B (1 = diffuse white).

    Returns
    -------
    numpy.ndarray
        ``...×3`` L*, a*, b* (float64).
    """
    xyz = np.asarray(rgb, dtype=np.float64) @ _RGB_TO_XYZ.T / _WHITE
    eps, kappa = 216 / 24389, 24389 / 27
    f = np.where(xyz > eps, np.cbrt(np.maximum(xyz, eps)), (kappa * xyz + 16) / 116)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], axis=-1)


def ciede2000(lab1: np.ndarray, lab2: np.ndarray, kl: float = 1.0, kc: float = 1.0, kh: float = 1.0) -> np.ndarray:
    """CIEDE2000 colour difference ΔE00 of CIELAB colours (elementwise, broadcast).

    Parameters
    ----------
    lab1, lab2 : array_like
        ``...×3`` L*, a*, b*.
    kl, kc, kh : float
        Parametric weights (1 for the reference conditions).

    Returns
    -------
    numpy.ndarray
        ΔE00, shape of the broadcast ``...``.

    References
    ----------
    Sharma, Wu & Dalal 2005, equations (1)–(22).
    """
    l1, a1, b1 = np.moveaxis(np.asarray(lab1, dtype=np.float64), -1, 0)
    l2, a2, b2 = np.moveaxis(np.asarray(lab2, dtype=np.float64), -1, 0)
    c1, c2 = np.hypot(a1, b1), np.hypot(a2, b2)
    cbar7 = ((c1 + c2) / 2) ** 7
    g = 0.5 * (1 - np.sqrt(cbar7 / (cbar7 + 25.0 ** 7)))
    a1p, a2p = (1 + g) * a1, (1 + g) * a2
    c1p, c2p = np.hypot(a1p, b1), np.hypot(a2p, b2)
    h1p = np.where((a1p == 0) & (b1 == 0), 0.0, np.degrees(np.arctan2(b1, a1p)) % 360)
    h2p = np.where((a2p == 0) & (b2 == 0), 0.0, np.degrees(np.arctan2(b2, a2p)) % 360)
    dl = l2 - l1
    dc = c2p - c1p
    zero = c1p * c2p == 0
    dh = h2p - h1p
    dh = np.where(dh > 180, dh - 360, np.where(dh < -180, dh + 360, dh))
    dh = np.where(zero, 0.0, dh)
    dhh = 2 * np.sqrt(c1p * c2p) * np.sin(np.radians(dh / 2))
    lbar = (l1 + l2) / 2
    cbar = (c1p + c2p) / 2
    hsum = h1p + h2p
    hbar = np.where(np.abs(h1p - h2p) <= 180, hsum / 2, np.where(hsum < 360, (hsum + 360) / 2, (hsum - 360) / 2))
    hbar = np.where(zero, hsum, hbar)
    t = (1 - 0.17 * np.cos(np.radians(hbar - 30)) + 0.24 * np.cos(np.radians(2 * hbar))
         + 0.32 * np.cos(np.radians(3 * hbar + 6)) - 0.20 * np.cos(np.radians(4 * hbar - 63)))
    dtheta = 30 * np.exp(-(((hbar - 275) / 25) ** 2))
    cbar7p = cbar ** 7
    rc = 2 * np.sqrt(cbar7p / (cbar7p + 25.0 ** 7))
    sl = 1 + 0.015 * (lbar - 50) ** 2 / np.sqrt(20 + (lbar - 50) ** 2)
    sc = 1 + 0.045 * cbar
    sh = 1 + 0.015 * cbar * t
    rt = -np.sin(np.radians(2 * dtheta)) * rc
    tl, tc, th = dl / (kl * sl), dc / (kc * sc), dhh / (kh * sh)
    return np.sqrt(tl ** 2 + tc ** 2 + th ** 2 + rt * tc * th)


def grey_cast_de(log_rg: np.ndarray | float, log_bg: np.ndarray | float, grey: float = MID_GREY) -> np.ndarray:
    """ΔE00 between a mid grey and the same grey tinted by channel ratios at equal luminance.

    The luminance fall-off is vignetting (corrected on its own); the cast is what is
    left: the grey's R/G and B/G multiplied by ``exp(log_rg)`` and ``exp(log_bg)``,
    rescaled to the grey's luminance Y.

    Parameters
    ----------
    log_rg, log_bg : array_like
        Natural-log changes of R/G and B/G (broadcast together).
    grey : float
        Linear level of the reference grey (default: L* ≈ 50).

    Returns
    -------
    numpy.ndarray
        ΔE00 (float64, broadcast shape).
    """
    u, v = np.broadcast_arrays(np.asarray(log_rg, dtype=np.float64), np.asarray(log_bg, dtype=np.float64))
    rgb = np.stack([np.exp(u), np.ones_like(u), np.exp(v)], axis=-1)
    rgb = grey * rgb / (rgb @ _RGB_TO_XYZ[1])[..., None]
    ref = linear_rgb_to_lab(np.array([grey, grey, grey]))
    return ciede2000(ref, linear_rgb_to_lab(rgb))
