"""Per-lens vignetting profiles: an embedded SQLite store that learns across frames.

A *profile* is the vignetting of one camera + lens at one focal-length bin, one
aperture bin and one frame aspect ratio (:class:`ProfileKey`).  It is stored in
frame-independent (normalised) units so that frames of any resolution of the same
sensor -- a RAW at full size, its half-size preview, a downscaled JPEG -- pool into
one profile (:func:`normalise`, :func:`denormalise`).

Learning
--------
Each frame's estimate (θ_i, Σ_i) is pooled in information form: the store keeps
Λ = Σ_i Σ_i⁻¹ and η = Σ_i Σ_i⁻¹ θ_i, and reports θ = Λ⁻¹ η with covariance Λ⁻¹
(the inverse-variance weighted mean).  The sums are kept *exactly* (every float64
is an integer multiple of a power of two, so they are accumulated as big
integers, see :class:`_Exact`): the result is the same whatever the order in which
concurrent workers add their frames.  Because one image's covariance understates
the frame-to-frame scatter (scene content biases each single-image estimate), the
store also keeps Welford running moments of θ and of the log2 field across frames
and reports that scatter (:attr:`Profile.scatter_sigma_ev`).  A profile is
*trusted* when it has at least :data:`TRUSTED_MIN_FRAMES` frames and its pooled
field uncertainty is below :data:`TRUSTED_SIGMA_EV` (its 2σ bound below
:data:`TRUSTED_BOUND_EV`): for a profile learned with frame evidence, the median's
σ (:mod:`vigproc.core.pooling`); without, the larger of the covariance-propagated σ and
scatter/√n.

Modules
-------
This module re-exports, one concept each:

- :mod:`vigproc.stores.profile_key`: :class:`ProfileKey`, its bins and the shared constants;
- :mod:`vigproc.core.information`: information-form pooling, exact sums, Welford moments;
- :mod:`vigproc.stores.profile`: :class:`Profile`, :class:`Shots`, the trust rule, interpolation;
- :mod:`vigproc.stores.profile_store`: the SQLite :class:`ProfileStore` (WAL, one
  ``BEGIN IMMEDIATE`` transaction per change) and its migrations;
- :mod:`vigproc.stores.profile_file`: the JSON files ``vigproc.profile/1``, ``/2``, ``/3``
  (``profiles/README.md``): :func:`export_profile`, :func:`import_profile`.

References
----------
S. Lyu, "Estimating Vignetting Function from a Single Image for Image
Authentication", ACM MM&Sec 2010 (the Kang-Weiss parameterisation used here).
"""

from __future__ import annotations

# The profile modules, one concept each; this module re-exports them so that
# ``from vigproc.stores.profiles import X`` keeps working.
from vigproc.errors import ProfileStoreError
from vigproc.core.normalised import (  # noqa: F401  (normalise, denormalise, fit_model_to_field: re-exported)
    FIELD_GRID,
    N_PARAMS,
    _field_and_jacobian,
    _field_sigma_ev,
    denormalise,
    fit_model_to_field,
    normalise,
)
from vigproc.core.information import (  # noqa: F401
    MAX_FILE_VARIANCE,
    RIDGE,
    _Exact,
    _Welford,
    _check_covariance,
    _scaled_pinv,
    fixed_indices,
    frame_information,
    pool_information,
    pool_mean,
)
from vigproc.stores.profile_key import (  # noqa: F401
    ANY,
    APERTURE_STEPS_PER_STOP,
    ASPECT_TOLERANCE,
    DB_ENV,
    DEFAULT_TIMEOUT,
    FILE_SCHEMA,
    FILE_SCHEMAS,
    FILE_SCHEMA_COLOUR,
    FILE_SCHEMA_GRID,
    FOCAL_OFFSET,
    FOCAL_STEPS_PER_OCTAVE,
    INTERPOLATION_REACH,
    MAX_ABS_ALPHA,
    MAX_ABS_CENTER,
    MAX_FALLOFF_EV,
    MAX_FILE_BYTES,
    MAX_FRAMES,
    MAX_GAIN_EV,
    MAX_LENS_ID,
    MAX_NOTES,
    MAX_SHAPE,
    PROVENANCES,
    ProfileKey,
    TRUSTED_BOUND_EV,
    TRUSTED_MIN_FRAMES,
    TRUSTED_SIGMA_EV,
    _APERTURE_RE,
    _ASPECT_RE,
    _FOCAL_RE,
    _LN2,
    _NAMED_ASPECTS,
    _NOMINAL_APERTURES,
    _aperture_index,
    _aperture_label,
    _aspect_value,
    _canonical_aperture,
    _canonical_aspect,
    _canonical_focal,
    _check_key,
    _check_lens_id,
    _focal_centre,
    _focal_index,
    _focal_label,
    _frame_size,
    _now,
    aperture_bin,
    aspect_label,
    focal_bin,
)
from vigproc.stores.profile import (  # noqa: F401
    CROP_RANGE,
    MAX_SHOT_VALUES,
    Profile,
    Shots,
    _MAX_NAME,
    _bin_value,
    _bracket,
    _histogram_add,
    _histogram_median,
    _is_trusted,
    _profile_stats,
    _valid_theta,
    interpolate_profiles,
)
from vigproc.stores.profile_file import (  # noqa: F401
    _UNITS,
    _file_covariance,
    _no_duplicates,
    _numbers,
    _opt_text,
    _reject_constant,
    _split_lens_id,
    _timestamp,
    export_profile,
    cast_records_from_dict,
    import_profile,
    profile_from_dict,
    profile_to_dict,
    read_profile_file,
)
from vigproc.stores.profile_store import (  # noqa: F401
    MAX_POOLED_FRAMES,
    MIGRATIONS,
    ProfileStore,
    SCHEMA_VERSION,
    _COLUMNS,
    _FIT_CACHE_SIZE,
    _blob,
    _fit_blob,
    _fit_from_blob,
    _migration_1,
    _migration_10,
    _migration_11,
    _migration_2,
    _migration_3,
    _migration_4,
    _migration_5,
    _migration_6,
    _migration_7,
    _migration_8,
    _migration_9,
    _unblob,
    default_db_path,
)

__all__ = [
    "ANY",
    "DB_ENV",
    "FILE_SCHEMA",
    "FILE_SCHEMA_COLOUR",
    "FILE_SCHEMA_GRID",
    "FILE_SCHEMAS",
    "N_PARAMS",
    "PROVENANCES",
    "SCHEMA_VERSION",
    "TRUSTED_BOUND_EV",
    "TRUSTED_MIN_FRAMES",
    "TRUSTED_SIGMA_EV",
    "Profile",
    "ProfileKey",
    "ProfileStore",
    "ProfileStoreError",
    "Shots",
    "aperture_bin",
    "aspect_label",
    "default_db_path",
    "denormalise",
    "export_profile",
    "fixed_indices",
    "fit_model_to_field",
    "focal_bin",
    "frame_information",
    "import_profile",
    "read_profile_file",
    "normalise",
    "pool_information",
    "pool_mean",
]
