"""A lens profile (:class:`Profile`), where its frames were shot (:class:`Shots`), the
trust rule and interpolation between neighbouring bins."""

from __future__ import annotations

import math
import unicodedata
from dataclasses import dataclass, field, fields, replace
from typing import Any, Sequence

import numpy as np

from vigproc.core.colour import ColourPool
from vigproc.core.gridfield import GridFieldModel
from vigproc.core.information import _Exact, _Welford
from vigproc.core.model import FitQuality, VignettingModel
from vigproc.core.normalised import (
    N_PARAMS,
    _field_and_jacobian,
    _field_sigma_ev,
    denormalise,
    fit_model_to_field,
    normalise,
)
from vigproc.errors import ModelError, ProfileStoreError
from vigproc.io.exif import LensKey
from vigproc.io.lensident import display_lens_id
from vigproc.stores.profile_grid import GridPool
from vigproc.stores.profile_key import (
    ANY,
    INTERPOLATION_REACH,
    MAX_FRAMES,
    PROVENANCES,
    ProfileKey,
    TRUSTED_MIN_FRAMES,
    TRUSTED_SIGMA_EV,
    _frame_size,
    _now,
    aspect_label,
)

# --------------------------------------------------------------------------- #
# profiles
# --------------------------------------------------------------------------- #


#: Distinct focal lengths (and crop factors) a profile's :class:`Shots` keeps at most.
MAX_SHOT_VALUES = 1000
#: Crop factors outside this range are an EXIF mistake (a 35-mm focal length of 11113 mm).
CROP_RANGE = (0.2, 15.0)
_MAX_NAME = 200


def _histogram_add(hist: tuple[tuple[float, int], ...], value: float, n: int = 1) -> tuple[tuple[float, int], ...]:
    d = dict(hist)
    if value in d or len(d) < MAX_SHOT_VALUES:
        d[value] = d.get(value, 0) + n
    return tuple(sorted(d.items()))


def _histogram_median(hist: tuple[tuple[float, int], ...]) -> float | None:
    total = sum(n for _, n in hist)
    if not total:
        return None
    seen = 0
    for v, n in hist:  # the lower median: a focal length a frame was really shot at
        seen += n
        if 2 * seen >= total:
            return v
    return hist[-1][0]


@dataclass(frozen=True)
class Shots:
    """How a profile's frames were shot, as their EXIF said: what a profile written for
    another program needs and its key does not keep (the key's names are casefolded and
    its focal length is a bin).

    Attributes
    ----------
    names : (make, model, lens, lens make)
        As the metadata spelt them (:attr:`vigproc.io.exif.LensKey.spelling`), of the
        latest frame that gave them; None when unknown.
    focal_mm : tuple of (focal length in mm, frames)
        The frames' real focal lengths (0.01 mm), ascending.
    crop : tuple of (crop factor, frames)
        The frames' 35-mm focal length over their focal length (0.001), ascending.
    """

    names: tuple[str | None, str | None, str | None, str | None] = (None, None, None, None)
    focal_mm: tuple[tuple[float, int], ...] = ()
    crop: tuple[tuple[float, int], ...] = ()

    @classmethod
    def of_frame(cls, lens_key: LensKey) -> Shots:
        """One frame's :class:`Shots` from its EXIF lens key."""
        names = tuple(getattr(lens_key, "spelling", None) or (None,) * 4)
        focal = lens_key.focal_mm
        focal_mm = ((round(float(focal), 2), 1),) if focal is not None and focal > 0 else ()
        crop: tuple[tuple[float, int], ...] = ()
        f35 = lens_key.focal_35mm
        if focal_mm and f35 is not None:
            c = round(float(f35) / float(focal), 3)
            crop = ((c, 1),) if CROP_RANGE[0] <= c <= CROP_RANGE[1] else ()
        return cls(names, focal_mm, crop)  # type: ignore[arg-type]

    def add(self, other: Shots) -> Shots:
        """These frames and ``other``'s; names from ``other`` where it has them."""
        focal, crop = self.focal_mm, self.crop
        for v, n in other.focal_mm:
            focal = _histogram_add(focal, v, n)
        for v, n in other.crop:
            crop = _histogram_add(crop, v, n)
        names = tuple(b if b is not None else a for a, b in zip(self.names, other.names))
        return Shots(names, focal, crop)  # type: ignore[arg-type]

    @property
    def focal_median(self) -> float | None:
        """The median focal length the frames were shot at (mm), or None."""
        return _histogram_median(self.focal_mm)

    @property
    def crop_factor(self) -> float | None:
        """The median crop factor the frames' EXIF gave, or None."""
        return _histogram_median(self.crop)

    def describe_focal(self) -> str | None:
        """``"70 mm"``, or ``"67-70 mm (median 70)"`` for frames shot at several; None
        when no frame gave its focal length."""
        med = self.focal_median
        if med is None:
            return None
        lo, hi = self.focal_mm[0][0], self.focal_mm[-1][0]
        if lo == hi:
            return f"{lo:g} mm"
        return f"{lo:g}-{hi:g} mm (median {med:g})"

    def to_json(self) -> dict[str, Any]:
        """The JSON object stored in the profile store and in profile files."""
        return {"make": self.names[0], "model": self.names[1], "lens": self.names[2], "lens_make": self.names[3],
                "focal_mm": [[v, n] for v, n in self.focal_mm], "crop": [[v, n] for v, n in self.crop]}

    @classmethod
    def from_json(cls, d: Any, where: str) -> Shots:
        """Validate :meth:`to_json`'s object (from a file or the store).

        Raises
        ------
        ProfileStoreError
            Naming ``where`` and the field.
        """
        if not isinstance(d, dict):
            raise ProfileStoreError(f"{where}: shots must be an object")
        names = []
        for k in ("make", "model", "lens", "lens_make"):
            v = d.get(k)
            if v is not None and not (isinstance(v, str) and 0 < len(v) <= _MAX_NAME and v.strip() == v
                                      and not any(unicodedata.category(ch) in ("Cc", "Cs") for ch in v)):
                raise ProfileStoreError(f"{where}: shots.{k} must be a one-line name of at most {_MAX_NAME} "
                                        "characters or null")
            names.append(v)

        def hist(k: str, lo: float, hi: float) -> tuple[tuple[float, int], ...]:
            v = d.get(k, [])
            ok = isinstance(v, list) and len(v) <= MAX_SHOT_VALUES and all(
                isinstance(e, list) and len(e) == 2 and isinstance(e[0], (int, float))
                and not isinstance(e[0], bool) and math.isfinite(e[0]) and lo <= e[0] <= hi
                and type(e[1]) is int and 1 <= e[1] <= MAX_FRAMES for e in v)
            if not ok:
                raise ProfileStoreError(f"{where}: shots.{k} must be a list of [value in {lo:g}..{hi:g}, frames]")
            out: tuple[tuple[float, int], ...] = ()
            for val, n in v:
                out = _histogram_add(out, float(val), n)
            return out

        return cls(tuple(names), hist("focal_mm", 0.01, 10_000.0), hist("crop", *CROP_RANGE))  # type: ignore[arg-type]


def _is_trusted(n_frames: int, sigma_ev: float | None) -> bool:
    return n_frames >= TRUSTED_MIN_FRAMES and sigma_ev is not None and sigma_ev < TRUSTED_SIGMA_EV


@dataclass(eq=False)
class Profile:
    """A lens profile: pooled model parameters in normalised units plus their evidence.

    Attributes
    ----------
    key : ProfileKey
    theta : ndarray (12,)
        Normalised (cx, cy, p1, p2, p3, α1..α7): centre in half-diagonals R, P in R⁻².
    covariance : ndarray (12, 12) or None
        Covariance of ``theta`` (Λ⁻¹ for learned profiles).
    info_matrix, info_vector : ndarray or None
        Pooled evidence Λ = Σ Λ_i and η = Σ Λ_i θ_i (None when no uncertainty is known).
    n_frames : int
        Frames the profile was learned from (for imports: as stated by the file).
    provenance : {"learned", "lensfun", "user"}
    created, updated : str
        UTC ISO 8601 timestamps.
    trusted : bool
        ``n_frames >= TRUSTED_MIN_FRAMES`` and ``field_sigma_ev < TRUSTED_SIGMA_EV``
        (imports may state it explicitly).
    field_sigma_ev : float or None
        Pooled uncertainty of log2 φ, RMS over a frame of the key's aspect, in EV:
        the larger of ``cov_sigma_ev`` and ``scatter_sigma_ev / √n``.
    cov_sigma_ev : float or None
        The same from ``covariance`` alone (first-order propagation).
    scatter_sigma_ev : float or None
        Frame-to-frame RMS spread of log2 φ across the learned frames, EV (≥ 2 frames).
    notes : str
    colour : ColourPool or None
        The frames' colour fields pooled (:class:`vigproc.core.colour.ColourPool`):
        per-channel shading a flat-field or a DNG's per-plane maps measured; None:
        colourless.
    grid : GridPool or None
        The flat frames' measured grid fields pooled node by node
        (:class:`vigproc.stores.profile_grid.GridPool`); None: none measured. When
        present, :meth:`model` corrects by it.
    shots : Shots or None
        How the frames were shot (their real focal lengths, crop factor and names as
        EXIF spelt them); None when unknown (a store or file from before schema v10/2).
    """

    key: ProfileKey
    theta: np.ndarray
    covariance: np.ndarray | None = None
    info_matrix: np.ndarray | None = None
    info_vector: np.ndarray | None = None
    n_frames: int = 0
    provenance: str = "learned"
    created: str = ""
    updated: str = ""
    trusted: bool = False
    field_sigma_ev: float | None = None
    cov_sigma_ev: float | None = None
    scatter_sigma_ev: float | None = None
    notes: str = ""
    shots: Shots | None = None
    colour: ColourPool | None = None
    grid: GridPool | None = None
    _exact: tuple[_Exact, _Exact] | None = field(default=None, repr=False)
    _welford: _Welford | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self.theta = np.asarray(self.theta, dtype=np.float64).copy()
        if self.theta.shape != (N_PARAMS,) or not np.all(np.isfinite(self.theta)):
            raise ProfileStoreError(f"profile {self.key}: θ must be {N_PARAMS} finite numbers")
        if self.provenance not in PROVENANCES:
            raise ProfileStoreError(f"profile {self.key}: provenance must be one of {PROVENANCES}, got {self.provenance!r}")
        now = _now()
        self.created = self.created or now
        self.updated = self.updated or self.created

    @property
    def theta_scatter(self) -> np.ndarray | None:
        """Sample covariance of the per-frame θ̃ (Welford), or None with fewer than 2 frames."""
        return self._welford.theta_scatter if self._welford is not None else None

    @property
    def theta_mean(self) -> np.ndarray | None:
        """Plain mean of the per-frame θ̃ (Welford), or None."""
        return self._welford.theta_mean.copy() if self._welford is not None and self._welford.n else None

    def label(self) -> str:
        """The profile as people read it (``profile list``, the log's "learned into profile
        ..."): the lens unescaped, and the focal lengths its frames were shot at instead of
        the bin's label once known (``@ 105 mm``, not ``@ f=112.4mm``)."""
        focal = self.shots.describe_focal() if self.shots is not None else None
        lens = display_lens_id(self.key.lens_id)  # escapes are for storage
        if focal is None:
            return str(self.key).replace(self.key.lens_id, lens, 1)
        return f"{lens} @ {focal} {self.key.aperture_bin} {self.key.aspect}"

    def mismatch(self, lens_key: LensKey | None) -> str | None:
        """Why this profile is not of the camera and lens a frame's EXIF names (``None``
        when it is, or when the EXIF names neither): a profile file given by hand may be
        of any lens, and applying another lens's fall-off is a silent miscorrection.

        Returns
        -------
        str or None
            A sentence naming both.
        """
        if not isinstance(lens_key, LensKey) or (lens_key.model is None and lens_key.lens is None):
            return None
        frame = lens_key.lens_id()
        mine = "|".join(self.key.lens_id.split("|")[:3])  # a lens unit's serial aside
        if mine == frame:
            return None
        return f"the profile is of {mine!r}, the frame's EXIF names {frame!r} (another camera or lens)"

    def model(self, width: int, height: int) -> VignettingModel:
        """The profile as a :class:`VignettingModel` for a ``width``×``height`` frame.

        With a grid field (:attr:`grid`): a :class:`vigproc.core.gridfield.GridFieldModel`
        whose parameters are the profile's θ and colour field (records, lensfun export,
        comparisons) and whose :meth:`~vigproc.core.gridfield.GridFieldModel.correct_image`
        divides each channel by the pooled grid, 0 at the optical centre.

        Raises
        ------
        ProfileStoreError
            If the frame size is not two positive integers, or the frame's aspect
            ratio is not the profile's.
        """
        width, height = _frame_size(width, height)
        if aspect_label(width / height) != self.key.aspect:
            raise ProfileStoreError(
                f"profile {self.key} is for aspect {self.key.aspect}; a {width}x{height} frame is "
                f"{aspect_label(width / height)} (a crop or a rotated frame)"
            )
        ev_rms = float(np.sqrt(np.mean(_field_and_jacobian(self.theta, self.key.aspect_ratio)[0] ** 2)))
        sigma = self.field_sigma_ev
        q = FitQuality(
            confidence=1.0 if self.trusted else 0.0,
            field_ev_rms=ev_rms,
            field_sigma_ev=sigma if sigma is not None else math.nan,
            snr=ev_rms / sigma if sigma else math.inf,
        )
        m = denormalise(self.theta, self.covariance, width, height, method=f"profile:{self.provenance}", quality=q)
        m = m if self.colour is None else replace(m, colour=self.colour.field(width, height))
        if self.grid is None:
            return m
        # the grid corrects; the Kang-Weiss θ and colour field stay for records and exports.
        # Centred on the optical centre, which a correction leaves as it is, as the model's would
        grid = self.grid.field(width, height).centred(m.colour.center if m.colour is not None else m.center)
        kw = {f.name: getattr(m, f.name) for f in fields(VignettingModel)}
        return GridFieldModel(**kw, grid=grid)


def _profile_stats(theta: np.ndarray, cov: np.ndarray | None, aspect: float,
                   welford: _Welford | None) -> tuple[float | None, float | None, float | None]:
    """(pooled σ, covariance σ, scatter σ) in EV."""
    cov_sigma = _field_sigma_ev(theta, cov, aspect) if cov is not None else None
    scatter = welford.scatter_sigma_ev if welford is not None else None
    parts = [s for s in (cov_sigma, scatter / math.sqrt(welford.n) if scatter is not None else None) if s is not None]
    pooled = max(parts) if parts else None
    return pooled, cov_sigma, scatter


def _valid_theta(theta: np.ndarray, aspect: float) -> bool:
    try:
        VignettingModel.from_vector(theta, 1000, 1000)
    except ModelError:
        return False
    return _field_and_jacobian(theta, aspect)[2] > 0.0


def _bin_value(label: str) -> float | None:
    """The number of a focal or aperture bin label ("f=23.6mm", "N=4.0"); None for "any"."""
    if label == ANY:
        return None
    return float(label[2:-2] if label.endswith("mm") else label[2:])


def _bracket(points: dict[float, Any], x: float, reach: float) -> list[tuple[Any, float]] | None:
    """Linear-interpolation weights at ``x`` between the nearest points on either side
    (a point at ``x`` itself: weight 1); None when ``x`` is not bracketed or the two
    points are further apart than ``reach``."""
    if x in points:
        return [(points[x], 1.0)]
    lo = max((p for p in points if p < x), default=None)
    hi = min((p for p in points if p > x), default=None)
    if lo is None or hi is None or hi - lo > reach:
        return None
    t = (x - lo) / (hi - lo)
    return [(points[lo], 1.0 - t), (points[hi], t)]


def interpolate_profiles(profiles: Sequence[Profile], key: ProfileKey, focal_mm: float,
                         fnumber: float) -> Profile | None:
    """A lens's profile at a focal length and f-number between its bins.

    Bilinear in (log2 focal length, stops = 2·log2 N), as lensfun interpolates its
    calibrations between focal lengths and apertures: at each of the two nearest
    aperture bins on either side of ``fnumber`` (or at its own), linear in log focal
    length between the nearest bins on either side (or its own), then linear across
    the two apertures; the log2 fields are combined, then written as the Kang-Weiss
    model. Never extrapolated; bins further apart than :data:`INTERPOLATION_REACH`
    are not bridged.

    Uncertainty: σ = hypot(Σ w_i σ_i, s), s the weighted RMS of the bins' fields
    about the interpolated one (how much the lens changes across the span, of which
    a linear interpolation may miss a part; ``vigproc bench profile-interp`` measures
    how often the error stays within it).

    Parameters
    ----------
    profiles : sequence of Profile
        Profiles of one lens and aspect (others are ignored).
    key : ProfileKey
        The key asked for (its lens id and aspect select the profiles).

    Returns
    -------
    Profile or None
        ``key``'s profile, notes naming the bins and weights; None when the bins do
        not bracket the request.
    """
    aspect = key.aspect_ratio
    grid: dict[float, dict[float, Profile]] = {}
    for p in profiles:
        f, n = _bin_value(p.key.focal_bin), _bin_value(p.key.aperture_bin)
        if p.key.lens_id != key.lens_id or p.key.aspect != key.aspect or f is None or n is None:
            continue
        grid.setdefault(2.0 * math.log2(n), {})[math.log2(f)] = p
    x, y = math.log2(focal_mm), 2.0 * math.log2(fnumber)
    reach_f, reach_n = INTERPOLATION_REACH
    levels = {}
    for level, row in grid.items():
        w = _bracket(row, x, reach_f)
        if w is not None:
            levels[level] = w
    across = _bracket(levels, y, reach_n)
    if across is None:
        return None
    weights: list[tuple[Profile, float]] = [(p, wa * wf) for row, wa in across for p, wf in row if wa * wf > 0]
    if len(weights) == 1:
        return weights[0][0]
    # the fields on a small frame of the key's aspect (natural log), combined
    gw, gh = 48, max(4, round(48 / aspect))
    fields = np.array([denormalise(p.theta, None, gw, gh).log_field((gh, gw)).ravel() for p, _ in weights])
    w = np.array([wt for _, wt in weights])
    mean = w @ fields
    spread = float(math.sqrt(max(float(w @ np.mean((fields - mean) ** 2, axis=1)), 0.0))) / math.log(2.0)
    sigmas = [p.field_sigma_ev for p, _ in weights]
    sigma = None if any(sg is None for sg in sigmas) else math.hypot(float(w @ np.array(sigmas)), spread)
    model, _ = fit_model_to_field(mean.reshape(gh, gw), gw, gh)
    provenances = {p.provenance for p, _ in weights}
    parts = ", ".join(f"{p.key.focal_bin} {p.key.aperture_bin} ({wt:.2f})" for p, wt in weights)
    return Profile(
        key=key, theta=normalise(model)[0], covariance=None, n_frames=sum(p.n_frames for p, _ in weights),
        provenance=provenances.pop() if len(provenances) == 1 else "user",
        trusted=all(p.trusted for p, _ in weights) and sigma is not None and sigma < TRUSTED_SIGMA_EV,
        field_sigma_ev=sigma, notes=f"interpolated from {parts}",
        colour=ColourPool.blend([(p.colour, wt) for p, wt in weights]),
        grid=GridPool.blend([(p.grid, wt) for p, wt in weights]),
    )
