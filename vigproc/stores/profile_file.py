"""Human-readable profile files: JSON of schema ``vigproc.profile/1``, ``/2``, ``/3`` and ``/4``
(documented in ``profiles/README.md``; examples in ``profiles/examples/``)."""

from __future__ import annotations

import builtins
import json
import math
import os
import stat
from datetime import datetime
from typing import Any, Sequence

import numpy as np

from vigproc.atomic import atomic_write_text
from vigproc.core.cast_series import check_record
from vigproc.core.colour import ColourPool
from vigproc.core.information import MAX_FILE_VARIANCE, _Exact, _check_covariance, _scaled_pinv, fixed_indices
from vigproc.core.model import N_ALPHA, PARAM_NAMES
from vigproc.core.normalised import N_PARAMS, denormalise
from vigproc.errors import ModelError, ProfileStoreError
from vigproc.io.exif import LensKey, normalise_text, unescape_key_part
from vigproc.stores.profile import Profile, Shots, _is_trusted, _profile_stats
from vigproc.stores.cast_store import MAX_CAST_FRAMES
from vigproc.stores.profile_grid import GridPool
from vigproc.stores.profile_key import (
    FILE_SCHEMA,
    FILE_SCHEMAS,
    FILE_SCHEMA_COLOUR,
    FILE_SCHEMA_GRID,
    MAX_ABS_ALPHA,
    MAX_ABS_CENTER,
    MAX_FALLOFF_EV,
    MAX_FILE_BYTES,
    MAX_FRAMES,
    MAX_GAIN_EV,
    MAX_NOTES,
    MAX_SHAPE,
    PROVENANCES,
    ProfileKey,
    _LN2,
    _canonical_aperture,
    _canonical_aspect,
    _canonical_focal,
    _check_lens_id,
)

# --------------------------------------------------------------------------- #
# human-readable files
# --------------------------------------------------------------------------- #

_UNITS = {
    "center": "frame half-diagonals R = hypot(W, H)/2, from the frame centre; x right, y down",
    "p": "R^-2 (P = [[p1, p2], [p2, p3]], r^2 = (v - c)^T P (v - c) with v in units of R)",
    "alpha": "dimensionless (G = 1 - sum_i alpha_i r^i)",
    "covariance": "of the free parameters: (cx, cy, p1, p2, p3, alpha1..alpha7) in that order and the units "
                  "above, without those listed in 'fixed'",
}


def _split_lens_id(lens_id: str) -> dict[str, str | None]:
    parts = lens_id.split("|")
    if len(parts) == 4 and parts[3].startswith("sn:"):
        return {"make": unescape_key_part(parts[0]), "model": unescape_key_part(parts[1]),
                "lens": unescape_key_part(parts[2]), "lens_serial": unescape_key_part(parts[3][3:])}
    if len(parts) == 3:
        return {"make": unescape_key_part(parts[0]), "model": unescape_key_part(parts[1]),
                "lens": unescape_key_part(parts[2])}
    return {}


def profile_to_dict(profile: Profile, cast_records: Sequence[dict] = ()) -> dict[str, Any]:
    """The ``vigproc.profile/2`` JSON object of ``profile``.

    Parameters
    ----------
    profile : Profile
    cast_records : sequence of dict
        The per-frame colour-cast records the store pooled for this profile
        (:func:`vigproc.core.cast_series.frame_record`); written as ``cast.frames`` so
        that the importing store reports the same cast.  Empty: no ``cast`` field.
    """
    th = [float(v) for v in profile.theta]
    cov = profile.covariance
    fixed = fixed_indices(cov) if cov is not None else ()
    free = [i for i in range(N_PARAMS) if i not in fixed]
    d: dict[str, Any] = {
        "schema": FILE_SCHEMA,
        "lens": {**_split_lens_id(profile.key.lens_id), "lens_id": profile.key.lens_id},
        "focal_bin": profile.key.focal_bin,
        "aperture_bin": profile.key.aperture_bin,
        "aspect": profile.key.aspect,
        "provenance": profile.provenance,
        "n_frames": int(profile.n_frames),
        "trusted": bool(profile.trusted),
        "model": {
            "units": dict(_UNITS),
            "coordinates": "half-diagonal",
            "center": th[0:2],
            "p": th[2:5],
            "alpha": th[5:],
        },
        # a parameter the fit held fixed is named, not written as a zero variance (which no reader
        # can tell from a broken covariance)
        "fixed": [PARAM_NAMES[i] for i in fixed],
        "covariance": None if cov is None else [[float(cov[i, j]) for j in free] for i in free],
        "field_sigma_ev": profile.field_sigma_ev,
        "scatter_sigma_ev": profile.scatter_sigma_ev,
        "created": profile.created,
        "updated": profile.updated,
        "notes": profile.notes,
        "shots": None if profile.shots is None else profile.shots.to_json(),
    }
    if profile.colour is not None:
        # a colour field needs a reader that knows it: /3 (a colourless profile stays /2)
        d["schema"] = FILE_SCHEMA_COLOUR
        d["colour"] = profile.colour.to_json()
    if profile.grid is not None:
        # a grid needs a reader that knows it: /4 (one without stays /2 or /3)
        d["schema"] = FILE_SCHEMA_GRID
        d["grid"] = profile.grid.to_json()
    if cast_records:
        # optional and ignored by readers that do not know it: no new schema
        d["cast"] = {"frames": [{"shift": np.asarray(r["shift"], dtype=float).tolist(),
                                 "se": np.asarray(r["se"], dtype=float).tolist()} for r in cast_records]}
    return d


def cast_records_from_dict(d: dict[str, Any], where: str = "profile") -> list[dict]:
    """The per-frame colour-cast records of a profile file's ``cast.frames``, validated.

    Returns
    -------
    list of dict
        Each ``{"shift": 4×2, "se": 4×2}``; empty when the file has no ``cast`` field.

    Raises
    ------
    ProfileStoreError
        ``cast`` is not ``{"frames": [record, ...]}`` of at most
        :data:`vigproc.stores.cast_store.MAX_CAST_FRAMES` valid records.
    """
    cast = d.get("cast")
    if cast is None:
        return []
    frames = cast.get("frames") if isinstance(cast, dict) else None
    if not isinstance(frames, list):
        raise ProfileStoreError(f"{where}: cast must be an object with a list 'frames'")
    if len(frames) > MAX_CAST_FRAMES:
        raise ProfileStoreError(f"{where}: cast.frames holds {len(frames)} records (at most {MAX_CAST_FRAMES})")
    out = []
    for i, rec in enumerate(frames):
        try:
            a, b = check_record(rec)
        except ValueError as exc:
            raise ProfileStoreError(f"{where}: cast.frames[{i}]: {exc}") from None
        out.append({"shift": a.tolist(), "se": b.tolist()})
    return out


def export_profile(profile: Profile, path: str | os.PathLike[str], cast_records: Sequence[dict] = ()) -> None:
    """Write ``profile`` (and its frames' colour-cast records, if given) as a
    ``vigproc.profile/2`` JSON file, atomically.

    Raises
    ------
    vigproc.errors.ImageWriteError
        If the file cannot be written (the old file, if any, is left intact).
    """
    text = json.dumps(profile_to_dict(profile, cast_records), indent=2, ensure_ascii=False, allow_nan=False) + "\n"
    atomic_write_text(path, text)


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number JSON allows")


def _no_duplicates(pairs: builtins.list[tuple[str, Any]]) -> dict[str, Any]:
    d: dict[str, Any] = {}
    for k, v in pairs:
        if k in d:
            raise ValueError(f"duplicate field {k!r}")
        d[k] = v
    return d


def _numbers(value: Any, n: int, where: str, name: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n:
        raise ProfileStoreError(f"{where}: {name} must be a list of {n} numbers")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise ProfileStoreError(f"{where}: {name} must contain only numbers")
    a = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ProfileStoreError(f"{where}: {name} contains NaN or Inf")
    return a


def _opt_text(d: dict[str, Any], name: str, where: str) -> str | None:
    v = d.get(name)
    if v is None:
        return None
    if not isinstance(v, str):
        raise ProfileStoreError(f"{where}: {name} must be a string or null, got {type(v).__name__}")
    return v


def _timestamp(d: dict[str, Any], name: str, where: str) -> str:
    v = _opt_text(d, name, where)
    if v is None:
        return ""
    try:
        datetime.fromisoformat(v.replace("Z", "+00:00"))
    except ValueError:
        raise ProfileStoreError(f"{where}: {name} {v!r} is not an ISO 8601 timestamp") from None
    return v


def profile_from_dict(d: Any, where: str = "profile") -> Profile:
    """Validate a ``vigproc.profile/1`` object and build the :class:`Profile`.

    Raises
    ------
    ProfileStoreError
        Naming ``where`` and the offending field.
    """
    if not isinstance(d, dict):
        raise ProfileStoreError(f"{where}: a profile must be a JSON object")
    schema = d.get("schema")
    if schema not in FILE_SCHEMAS:
        raise ProfileStoreError(f"{where}: schema must be one of {', '.join(map(repr, FILE_SCHEMAS))}, got {schema!r}")
    for req in ("lens", "focal_bin", "aperture_bin", "aspect", "provenance", "model"):
        if req not in d:
            raise ProfileStoreError(f"{where}: missing field {req!r}")

    # identity
    lens = d["lens"]
    if not isinstance(lens, dict):
        raise ProfileStoreError(f"{where}: lens must be an object with make, model, lens and/or lens_id")
    names = {k: _opt_text(lens, k, f"{where}: lens") for k in ("make", "model", "lens", "lens_serial")}
    norm = {k: (normalise_text(v) if v is not None else None) for k, v in names.items()}
    derived = None
    if norm["model"] is not None or norm["lens"] is not None:
        derived = LensKey(make=norm["make"], model=norm["model"], lens=norm["lens"], lens_serial=norm["lens_serial"]).lens_id(
            with_serial=norm["lens_serial"] is not None
        )
    lens_id = lens.get("lens_id")
    if lens_id is None:
        if derived is None:
            raise ProfileStoreError(f"{where}: lens needs lens_id or at least model or lens")
        lens_id = derived
    else:
        try:
            _check_lens_id(lens_id)
        except ProfileStoreError as exc:
            raise ProfileStoreError(f"{where}: lens.lens_id: {exc}") from None
        if derived is not None and derived != lens_id:
            raise ProfileStoreError(
                f"{where}: lens.lens_id {lens_id!r} does not match make/model/lens (which give {derived!r})"
            )

    try:
        key = ProfileKey(
            lens_id,
            _canonical_focal(d["focal_bin"], where),
            _canonical_aperture(d["aperture_bin"], where),
            _canonical_aspect(d["aspect"], where),
        )
    except ProfileStoreError as exc:
        msg = str(exc)
        raise ProfileStoreError(msg if msg.startswith(where) else f"{where}: {msg}") from None

    prov = d["provenance"]
    if prov not in PROVENANCES:
        raise ProfileStoreError(f"{where}: provenance must be one of {', '.join(PROVENANCES)}, got {prov!r}")
    n_frames = d.get("n_frames", 0)
    if isinstance(n_frames, bool) or not isinstance(n_frames, int) or not 0 <= n_frames <= MAX_FRAMES:
        raise ProfileStoreError(f"{where}: n_frames must be an integer 0..{MAX_FRAMES}, got {n_frames!r}")
    trusted_claim = d.get("trusted")
    if trusted_claim is not None and not isinstance(trusted_claim, bool):
        raise ProfileStoreError(f"{where}: trusted must be true, false or absent")
    notes = d.get("notes", "")
    if notes is None:
        notes = ""
    if not isinstance(notes, str) or len(notes) > MAX_NOTES:
        raise ProfileStoreError(f"{where}: notes must be a string of at most {MAX_NOTES} characters")

    # parameters
    m = d["model"]
    if not isinstance(m, dict):
        raise ProfileStoreError(f"{where}: model must be an object")
    for req in ("coordinates", "center", "p", "alpha"):
        if req not in m:
            raise ProfileStoreError(f"{where}: missing field 'model.{req}'")
    if m["coordinates"] != "half-diagonal":
        raise ProfileStoreError(
            f"{where}: model.coordinates must be 'half-diagonal' (parameters in frame half-diagonals), got {m['coordinates']!r}"
        )
    c = _numbers(m["center"], 2, where, "model.center")
    p = _numbers(m["p"], 3, where, "model.p")
    a = _numbers(m["alpha"], N_ALPHA, where, "model.alpha")
    if np.any(np.abs(c) > MAX_ABS_CENTER):
        raise ProfileStoreError(f"{where}: model.center {c.tolist()} is absurd (more than {MAX_ABS_CENTER} half-diagonals off centre)")
    if np.any(np.abs(p) > MAX_SHAPE):
        raise ProfileStoreError(f"{where}: model.p {p.tolist()} is absurd (|p| > {MAX_SHAPE:g} R^-2)")
    if np.any(np.abs(a) > MAX_ABS_ALPHA):
        raise ProfileStoreError(f"{where}: model.alpha {a.tolist()} is absurd (|alpha| > {MAX_ABS_ALPHA:g})")
    theta = np.concatenate([c, p, a])
    # P PSD and G > 0 inside the frame, checked through the model itself on a small grid
    asp = key.aspect_ratio
    h = 120
    w = max(2, round(h * asp))
    try:
        lf = denormalise(theta, None, w, h).log_field((h, w)) / _LN2
    except ModelError as exc:
        raise ProfileStoreError(f"{where}: model: {exc}") from None
    if lf.min() < -MAX_FALLOFF_EV or lf.max() > MAX_GAIN_EV:
        raise ProfileStoreError(
            f"{where}: model: the field spans {lf.min():.2f}..{lf.max():.2f} EV inside the frame "
            f"(absurd: allowed -{MAX_FALLOFF_EV:g}..+{MAX_GAIN_EV:g} EV)"
        )

    cov_a = _file_covariance(d, schema, where)
    sigma = d.get("field_sigma_ev")
    if sigma is not None and (isinstance(sigma, bool) or not isinstance(sigma, (int, float))
                              or not (math.isfinite(sigma) and 0 <= sigma <= MAX_FALLOFF_EV)):
        raise ProfileStoreError(f"{where}: field_sigma_ev must be a number of EV in 0..{MAX_FALLOFF_EV:g} or null")
    scatter = d.get("scatter_sigma_ev")
    if scatter is not None and (isinstance(scatter, bool) or not isinstance(scatter, (int, float))
                                or not (math.isfinite(scatter) and 0 <= scatter <= MAX_FALLOFF_EV)):
        raise ProfileStoreError(f"{where}: scatter_sigma_ev must be a number of EV in 0..{MAX_FALLOFF_EV:g} or null")
    shots = None if d.get("shots") is None else Shots.from_json(d["shots"], where)
    colour = None
    if d.get("colour") is not None:
        if schema not in (FILE_SCHEMA_COLOUR, FILE_SCHEMA_GRID):
            raise ProfileStoreError(f"{where}: a colour field needs schema {FILE_SCHEMA_COLOUR!r} or "
                                    f"{FILE_SCHEMA_GRID!r}, got {schema!r}")
        try:
            colour = ColourPool.from_json(d["colour"])
        except ModelError as exc:
            raise ProfileStoreError(f"{where}: colour: {exc}") from None
    grid = None
    if d.get("grid") is not None:
        if schema != FILE_SCHEMA_GRID:
            raise ProfileStoreError(f"{where}: a grid field needs schema {FILE_SCHEMA_GRID!r}, got {schema!r}")
        try:
            grid = GridPool.from_json(d["grid"])
            grid.check_aspect(key.aspect_ratio, key.aspect)
        except ModelError as exc:
            raise ProfileStoreError(f"{where}: grid: {exc}") from None
    created = _timestamp(d, "created", where)
    updated = _timestamp(d, "updated", where)

    exact = None
    lam = eta = None
    if cov_a is not None:
        lam = _scaled_pinv(cov_a, f"{where}: covariance", allow_fixed=True)
        eta = lam @ theta
        exact = (_Exact.from_array(lam), _Exact.from_array(eta))
    pooled, cov_sigma, _ = _profile_stats(theta, cov_a, asp, None)
    if sigma is not None and cov_a is not None:
        # the σ the profile was trusted on (a learned one's is its frames' median's, which its
        # covariance alone does not give): the file travels with the same trust
        pooled = float(sigma)
    trusted = trusted_claim if trusted_claim is not None else _is_trusted(n_frames, pooled)
    return Profile(
        key=key, theta=theta, covariance=cov_a, info_matrix=lam, info_vector=eta, n_frames=n_frames,
        provenance=prov, created=created, updated=updated or created, trusted=trusted,
        field_sigma_ev=pooled, cov_sigma_ev=cov_sigma,
        # the spread its frames showed, as the file states it (kept so that a re-export says it too)
        scatter_sigma_ev=None if scatter is None else float(scatter), notes=notes, shots=shots,
        colour=colour, grid=grid, _exact=exact,
    )


def _file_covariance(d: dict[str, Any], schema: str, where: str) -> np.ndarray | None:
    """The 12×12 covariance of a profile file (zero rows and columns for its fixed
    parameters), or None.  ``/1``: a 12×12 matrix; ``/2``: ``fixed`` names the
    parameters held fixed and the matrix covers the others, in :data:`PARAM_NAMES` order."""
    cov = d.get("covariance")
    fixed_names = d.get("fixed", [])
    if schema == "vigproc.profile/1":
        fixed_names = []
    if not (isinstance(fixed_names, list) and all(isinstance(v, str) for v in fixed_names)):
        raise ProfileStoreError(f"{where}: fixed must be a list of parameter names")
    unknown = [v for v in fixed_names if v not in PARAM_NAMES]
    if unknown or len(set(fixed_names)) != len(fixed_names):
        raise ProfileStoreError(f"{where}: fixed {fixed_names!r} must name distinct parameters of "
                                f"{', '.join(PARAM_NAMES)}")
    if cov is None:
        return None
    free = [i for i, name in enumerate(PARAM_NAMES) if name not in fixed_names]
    n = len(free)
    if not free:
        raise ProfileStoreError(f"{where}: fixed names every parameter; the covariance must be null")
    if not (isinstance(cov, list) and len(cov) == n and all(isinstance(r, list) and len(r) == n for r in cov)):
        raise ProfileStoreError(f"{where}: covariance must be a {n}x{n} list of lists (the parameters not "
                                "in 'fixed') or null")
    sub = np.asarray([_numbers(r, n, where, "covariance") for r in cov])
    full = np.zeros((N_PARAMS, N_PARAMS))
    full[np.ix_(free, free)] = sub
    if fixed_names and not np.all(np.diag(sub) > 0):
        raise ProfileStoreError(f"{where}: covariance has a non-positive variance (a parameter held fixed "
                                "belongs in 'fixed')")
    # /1 files of learned profiles wrote a fixed parameter as an all-zero row: read it as fixed
    cov_a = _check_covariance(full, f"{where}: covariance", allow_fixed=True)
    if float(np.max(np.diag(cov_a))) > MAX_FILE_VARIANCE:  # a standard deviation of 10⁴ says nothing
        raise ProfileStoreError(f"{where}: covariance has a variance of {float(np.max(np.diag(cov_a))):.3g}, "
                                f"above {MAX_FILE_VARIANCE:g} (use null for an unknown uncertainty)")
    return cov_a


def import_profile(path: str | os.PathLike[str]) -> Profile:
    """Read and validate a profile file: :func:`read_profile_file`'s profile."""
    return read_profile_file(path)[0]


def read_profile_file(path: str | os.PathLike[str]) -> tuple[Profile, list[dict]]:
    """Read and validate a ``vigproc.profile/2`` (or ``/1``) file (does not touch any store).

    Checks: size, JSON syntax (NaN/Infinity and duplicate fields rejected), schema,
    required fields and their types, bin labels, provenance, finite parameters
    within sane bounds, P positive semi-definite, G > 0 and a plausible fall-off
    inside the frame, covariance symmetric PSD.  A ``trusted`` value in the file is
    honoured; without it, trust follows the rule of learned profiles.

    Returns
    -------
    tuple of (Profile, list of dict)
        The profile and the per-frame colour-cast records its ``cast`` field carries
        (:func:`cast_records_from_dict`; empty without one).

    Raises
    ------
    ProfileStoreError
        Naming the file and the field.
    """
    where = str(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):  # a FIFO or device would block or never end
            raise ProfileStoreError(f"{where}: not a regular file")
        size = st.st_size
        if size > MAX_FILE_BYTES:
            raise ProfileStoreError(f"{where}: {size} bytes is too large for a profile file (limit {MAX_FILE_BYTES})")
        with open(path, "rb") as fh:
            raw = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ProfileStoreError(f"cannot read profile file {where}: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
        d = json.loads(text, parse_constant=_reject_constant, object_pairs_hook=_no_duplicates)
    except UnicodeDecodeError as exc:
        raise ProfileStoreError(f"{where}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except (json.JSONDecodeError, ValueError, RecursionError) as exc:  # RecursionError: absurdly nested
        raise ProfileStoreError(f"{where}: not valid profile JSON: {exc}") from None
    profile = profile_from_dict(d, where)
    return profile, cast_records_from_dict(d, where)
