"""A peer estimator for the benchmarks: radial-gradient symmetry (Zheng et al. 2013).

The issue quotes Zheng et al.'s method at ≈ 0.08 EV on the lensfun protocol and
0.11 EV of invented fall-off on vignetting-free photos, measured on other images.
To compare on the *same* photos and protocol, the benchmarks run this
reimplementation of its core assumption: in a vignetting-free photo, radial
log-gradients are symmetric about zero, so a robust fit of their mean is the
lens's fall-off.

What it is, and what it is not:

- a centred, even polynomial log φ(r) = Σ_{i=1..3} a_i r^{2i} (r in half-diagonals),
  fitted by IRLS with the hyper-Laplacian loss |e|^0.8 (their natural-image
  gradient prior) to the radial component of central-difference log-gradients of a
  binned working copy;
- not their whole method: no segmentation, no KL-divergence asymmetry measure, no
  iteration between estimate and symmetry test, no colour handling.

Being centred and circular is its strength on real lenses and its limit: it cannot
follow Lyu's off-centre, elliptical Table 1 settings.

References
----------
Y. Zheng, S. Lin, S. B. Kang, R. Xiao, J. Gee, C. Kambhamettu, "Single-image
vignetting correction from gradient distribution symmetries", IEEE TPAMI 35(6),
2013, Sections 3–4 (radial gradient symmetry; the |·|^0.8 prior of Eq. 5).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from vigproc.core.model import VignettingModel
from vigproc.core.robust import RobustSettings, working_copy
from vigproc.core.scene import frame_grid

#: Exponent of the hyper-Laplacian gradient prior (Zheng et al., Eq. 5).
EXPONENT = 0.8


def radial_polynomial(lum: np.ndarray, work_size: int = 120, order: int = 3, iters: int = 15,
                      eps: float = 1e-3) -> np.ndarray:
    """Coefficients a_1..a_order of log φ(r) = Σ a_i r^{2i} (natural log, r in half-diagonals).

    Parameters
    ----------
    lum : ndarray, H×W, linear luminance
    work_size : int
        Long side of the binned working copy.
    order : int
        Number of even terms.
    iters : int
        IRLS iterations.
    eps : float
        Residuals below this (log units) get the weight of ``eps`` (keeps IRLS finite).

    Returns
    -------
    ndarray of shape (order,)
    """
    wc = working_copy(np.asarray(lum, dtype=np.float64), RobustSettings(work_size=work_size))
    L, valid = wc.L, wc.valid
    X, Y = np.meshgrid(wc.xs, wc.ys)
    r = np.hypot(X, Y)
    gx = np.zeros_like(L)
    gy = np.zeros_like(L)
    gx[:, 1:-1] = (L[:, 2:] - L[:, :-2]) / 2
    gy[1:-1] = (L[2:] - L[:-2]) / 2
    ok = valid & (r > 0.05)  # the radial direction is undefined at the centre
    ok[:, [0, -1]] = False
    ok[[0, -1], :] = False
    ok[:, 1:-1] &= valid[:, 2:] & valid[:, :-2]
    ok[1:-1] &= valid[2:] & valid[:-2]
    g = ((gx * X + gy * Y) / np.maximum(r, 1e-9))[ok]  # radial log-gradient per bin
    rr = r[ok]
    step = wc.xs[1] - wc.xs[0]  # the bin size in half-diagonals
    D = np.stack([2 * i * rr ** (2 * i - 1) * step for i in range(1, order + 1)], axis=1)
    a = np.zeros(order)
    if g.size < 4 * order:
        return a
    for _ in range(iters):
        e = g - D @ a
        wgt = np.maximum(np.abs(e), eps) ** (EXPONENT - 2.0)
        a = np.linalg.solve(D.T @ (D * wgt[:, None]) + 1e-9 * np.eye(order), D.T @ (wgt * g))
    return a


def estimate_rgs(lum: np.ndarray) -> VignettingModel:
    """Radial-gradient-symmetry peer: the centred radial fall-off as a Kang-Weiss model.

    The polynomial is clamped to log φ ≤ 0 (a vignetting field does not brighten)
    and fitted with :func:`vigproc.core.normalised.fit_model_to_field`, so that the
    benchmarks score it exactly as they score vigproc's own models.

    Parameters
    ----------
    lum : ndarray, H×W, linear luminance

    Returns
    -------
    VignettingModel
        For the H×W frame, ``method="rgs"``.
    """
    from vigproc.core.normalised import fit_model_to_field

    h, w = lum.shape
    a = radial_polynomial(lum)
    xs, ys, _, _ = frame_grid(w / h)
    X, Y = np.meshgrid(xs, ys)
    r2 = X * X + Y * Y
    F = np.minimum(sum(a[i] * r2 ** (i + 1) for i in range(len(a))), 0.0)
    if not np.any(F < 0):
        return VignettingModel(w, h, method="rgs")
    model, _ = fit_model_to_field(F, w, h)
    return replace(model, method="rgs")


# --------------------------------------------------------------------------- #
# the published peer (Zheng et al.'s method in GUOYI1/Vignetting_corrector's C++)
# --------------------------------------------------------------------------- #

#: Environment variable naming the built peer (scripts/build_rgs_peer.sh).
PEER_ENV = "VIGPROC_RGS_PEER"


def _write_pgm(path, g8: np.ndarray) -> None:
    h, w = g8.shape
    with open(path, "wb") as fh:
        fh.write(f"P5\n{w} {h}\n255\n".encode("ascii"))
        fh.write(np.ascontiguousarray(g8, dtype=np.uint8).tobytes())


def _read_pfm(path) -> np.ndarray:
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"Pf":
            raise ValueError("not a grey PFM")
        w, h = (int(v) for v in fh.readline().split())
        scale = float(fh.readline())
        data = np.frombuffer(fh.read(4 * w * h), dtype="<f4" if scale < 0 else ">f4")
    return data.reshape(h, w)[::-1].astype(np.float64)  # PFM rows are bottom-to-top


def published_rgs(exe: str, encoding: str = "linear", timeout: float = 60.0):
    """The published C++ of Zheng et al.'s radial-gradient symmetry as a bench
    estimator (``benchmarks.clean.Estimator``), run as a separate process.

    Parameters
    ----------
    exe : str
        The ``rgs_peer`` built by ``scripts/build_rgs_peer.sh`` from a snapshot of
        GUOYI1/Vignetting_corrector (never part of vigproc).
    encoding : {"linear", "srgb"}
        What the peer is given, as 8 bits: the linear frame scaled to its 99.9th
        percentile, or that frame sRGB-encoded (what a JPEG holds); for "srgb" its
        field is taken back to linear light with the sRGB curve's mean exponent 2.2.

    Returns
    -------
    callable
        lum (H×W linear) -> ``benchmarks.clean.Estimate``.
    """
    import subprocess
    import tempfile
    from pathlib import Path

    from benchmarks.clean import Estimate
    from vigproc.io.images import linear_to_srgb

    def run(lum: np.ndarray, _field=None) -> Estimate:
        a = np.asarray(lum, dtype=np.float64)
        a = np.clip(a / max(float(np.percentile(a, 99.9)), 1e-12), 0.0, 1.0)
        if encoding == "srgb":
            a = linear_to_srgb(a)
        g8 = np.round(a * 255.0).astype(np.uint8)
        with tempfile.TemporaryDirectory(prefix="vigproc-rgs-") as tmp:
            src, dst = Path(tmp) / "in.pgm", Path(tmp) / "out.pfm"
            _write_pgm(src, g8)
            subprocess.run([exe, str(src), str(dst)], check=True, timeout=timeout,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            f = _read_pfm(dst)
        lf = np.log(np.maximum(f, 1e-6))
        if encoding == "srgb":
            lf = 2.2 * lf
        return Estimate(lf)

    return run
