"""The stable pipeline API under the name earlier releases gave it.

Photo pipelines written against ``from vigproc.api import Pipeline`` keep working: this
module re-exports :mod:`vigproc.frontends.api` (also ``vigproc.Pipeline``), where the
front ends live since the package became layers.
"""

from vigproc.frontends.api import *  # noqa: F401,F403  (the stable names)
from vigproc.frontends.api import __all__  # noqa: F401
