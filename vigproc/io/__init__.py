"""Image and metadata input/output: pixels in linear light, EXIF, metadata carried into outputs, DNG opcodes.

``read_image`` and ``write_image`` (:mod:`vigproc.io.images`) are importable from here, as
they were before the package became layers; they load when first used, so importing
another part of :mod:`vigproc.io` does not load OpenImageIO and rawpy.
"""

_IMAGES = ("ImageInfo", "read_image", "write_image")


def __getattr__(name: str):
    if name in _IMAGES:
        from vigproc.io import images

        return getattr(images, name)
    raise AttributeError(f"module 'vigproc.io' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_IMAGES])
