"""Image input/output: read any supported image as float32 *linear* light, write atomically.

The public import path of vigproc's image I/O; the code lives in one module per concept:

* :mod:`vigproc.io.image_read`: reading (JPEG, PNG, TIFF and OpenEXR through OpenImageIO,
  camera RAW through LibRaw), the format decided by content, the memory budget;
* :mod:`vigproc.io.transfer`: transfer curves (sRGB, gamma, linear) and which one a file's
  metadata declares;
* :mod:`vigproc.io.image_write`: atomic writing of TIFF, PNG, OpenEXR and JPEG;
* :mod:`vigproc.io.jpeg`: a JPEG's IJG quality.
"""

from __future__ import annotations

# re-exported: callers import these from vigproc.io.images (the private names too, for tests)
from vigproc.io.image_read import (DEFAULT_MEMORY_BUDGET, HEAD_BYTES, MEMORY_BUDGET_ENV,  # noqa: F401
                                   RAW_DEVELOP, RAW_EXTENSIONS, READ_BAND, SUPPORTED_OIIO_FORMATS, EncodedImage,
                                   ImageInfo, PathLike, _read_pixels, _read_raw, memory_budget, read_cfa_planes,
                                   read_encoded, read_image)
from vigproc.io.image_write import FLOAT_MAX, ROOM_MARGIN, _stored_values, size_bound, write_image  # noqa: F401
from vigproc.io.jpeg import DEFAULT_JPEG_QUALITY, jpeg_quality  # noqa: F401
from vigproc.io.transfer import (LINEAR_TIFF_MARKER, _quantise, encode_steps, linear_to_srgb,  # noqa: F401
                                 recorded_transfer, srgb_to_linear)

__all__ = [
    "ImageInfo",
    "LINEAR_TIFF_MARKER",
    "recorded_transfer",
    "RAW_EXTENSIONS",
    "SUPPORTED_OIIO_FORMATS",
    "DEFAULT_MEMORY_BUDGET",
    "MEMORY_BUDGET_ENV",
    "linear_to_srgb",
    "memory_budget",
    "read_image",
    "srgb_to_linear",
    "write_image",
]
