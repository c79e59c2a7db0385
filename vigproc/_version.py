"""vigproc's version, in a leaf module: code inside the package reads it from here
instead of importing the package itself (which would point an import upward)."""

__version__ = "0.1.0"
