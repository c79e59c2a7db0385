"""A profile's measured grid field (:class:`GridPool`): the grid fields of its flat
frames (:class:`vigproc.core.gridfield.GridField`) pooled node by node, its store column
and its place in profile files.

Pooling
-------
In information form, node by node and channel by channel, as a profile pools its θ and
its colour field: each frame adds Σ 1/σ² and Σ v/σ² at every node (v its ln φ_c there,
σ its 1-σ); the pooled field is their ratio, its 1-σ 1/√(Σ 1/σ²). A frame's grid has
each channel's mean removed (white balance), so the frames' values are comparable node
by node. Grids of different node counts (frames of one aspect bin whose sides round
differently) are resampled bilinearly onto the pool's nodes.

Interpolation
-------------
Between focal lengths and apertures (:func:`vigproc.stores.profile.interpolate_profiles`),
nodewise in the same form: the pooled values combined with the interpolation's weights,
Σ w_i v_i, variance Σ w_i σ_i² (the colour pool's rule, :meth:`ColourPool.blend`); None
unless every bin has a grid.

References
----------
Adobe, *Digital Negative (DNG) Specification* 1.4.0.0, "GainMap" (the grid's node
placement and interpolation).
"""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass
from typing import Any

import numpy as np

from vigproc.core.gridfield import GridField, bilinear
from vigproc.errors import ModelError

#: Smallest σ of a node pooled (a frame stating none, or zero, gets this), natural log.
POOL_SIGMA_FLOOR = 1e-4
#: Largest node count per side a stored or imported pool may have (the default is 33).
MAX_NODES = 129


def _array(name: str, v: Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ModelError(f"grid pool {name} must be numbers") from None
    if a.ndim != 3 or a.shape[2] != 3 or not (2 <= a.shape[0] <= MAX_NODES and 2 <= a.shape[1] <= MAX_NODES):
        raise ModelError(f"grid pool {name} must be ny×nx×3 with 2..{MAX_NODES} nodes a side, got {a.shape}")
    if shape is not None and a.shape != shape:
        raise ModelError(f"grid pool {name} has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise ModelError(f"grid pool {name} holds NaN or Inf")
    return a


def _resample(a: np.ndarray, ny: int, nx: int) -> np.ndarray:
    """``a`` (ny'×nx'×3 on nodes spanning the frame) at ``ny``×``nx`` nodes, bilinear."""
    if a.shape[:2] == (ny, nx):
        return a
    return bilinear(a, np.linspace(0.0, 1.0, ny), np.linspace(0.0, 1.0, nx))


@dataclass(frozen=True, eq=False)
class GridPool:
    """Grid fields of several frames of one lens setting, pooled node by node in
    information form.

    Attributes
    ----------
    info : ndarray (ny, nx, 3)
        Σ 1/σ² per node and channel.
    weighted : ndarray (ny, nx, 3)
        Σ v/σ².
    n : int
        Frames pooled.
    source : str
    """

    info: Any
    weighted: Any
    n: int = 1
    source: str = ""

    def __post_init__(self) -> None:
        info = _array("info", self.info)
        if np.any(info <= 0):
            raise ModelError("grid pool info must be > 0 at every node")
        object.__setattr__(self, "info", info)
        object.__setattr__(self, "weighted", _array("weighted", self.weighted, info.shape))
        if isinstance(self.n, bool) or not isinstance(self.n, (int, np.integer)) or self.n < 1:
            raise ModelError(f"grid pool n must be a positive integer, got {self.n!r}")
        object.__setattr__(self, "n", int(self.n))
        object.__setattr__(self, "source", str(self.source))
        # the field it stands for must be one a GridField accepts (not 12 EV across the frame)
        GridField(2, 2, self.weighted / self.info)

    @property
    def nodes(self) -> tuple[int, int]:
        """(nx, ny)."""
        return (self.info.shape[1], self.info.shape[0])

    def check_aspect(self, aspect: float, label: str) -> None:
        """Check that the nodes are those of a frame of ``aspect`` (width / height): the
        short side's count within one node of the long side's in proportion, as
        :func:`vigproc.core.gridfield.flat_grid` lays them out.  Nodes lie on the frame's
        edges, so a grid of another frame shape would be stretched over this one.

        Parameters
        ----------
        aspect : float
            The profile's frame aspect ratio (width / height).
        label : str
            Its name, for the message (e.g. ``"3:2"``).

        Raises
        ------
        ModelError
            The nodes are not a grid of such a frame.
        """
        nx, ny = self.nodes
        long_side, short = (nx, ny) if aspect >= 1 else (ny, nx)
        expected = max(2, round(long_side * min(aspect, 1 / aspect)))
        if abs(short - expected) > 1:
            raise ModelError(f"a grid of {nx}x{ny} nodes is not one of a {label} frame "
                             f"(about {long_side}x{expected} nodes, long side first)")

    @classmethod
    def of(cls, grid: GridField) -> GridPool:
        """One frame's grid as a pool."""
        s = np.maximum(grid.sigma if grid.sigma is not None else 0.0, POOL_SIGMA_FLOOR)
        info = np.broadcast_to(1.0 / (s * s), grid.log_field.shape).copy()
        return cls(info, info * grid.log_field, 1, grid.source)

    def add(self, other: GridPool) -> GridPool:
        """These frames and ``other``'s (resampled onto these nodes if it has others)."""
        ny, nx = self.info.shape[:2]
        o_info = _resample(other.info, ny, nx)
        o_mean = _resample(other.weighted / other.info, ny, nx)
        src = self.source if self.source == other.source else "pooled"
        return GridPool(self.info + o_info, self.weighted + o_info * o_mean, self.n + other.n, src)

    def field(self, width: int, height: int) -> GridField:
        """The pooled field of a ``width``×``height`` frame (σ per node from the pooled
        information)."""
        return GridField(width, height, self.weighted / self.info, 1.0 / np.sqrt(self.info), self.source)

    @staticmethod
    def blend(parts: list[tuple[GridPool | None, float]]) -> GridPool | None:
        """Linear interpolation of pools (a profile between focal lengths and apertures),
        node by node: Σ w_i v_i, variance Σ w_i σ_i²; on the first pool's nodes; None
        unless all have one."""
        if not parts or any(p is None for p, _ in parts):
            return None
        ny, nx = parts[0][0].info.shape[:2]
        mean = np.zeros((ny, nx, 3))
        var = np.zeros((ny, nx, 3))
        for p, w in parts:
            mean += w * _resample(p.weighted / p.info, ny, nx)
            var += w * _resample(1.0 / p.info, ny, nx)
        info = 1.0 / np.maximum(var, POOL_SIGMA_FLOOR ** 2)
        return GridPool(info, info * mean, sum(p.n for p, _ in parts), "interpolated")

    def to_json(self) -> dict[str, Any]:
        return {"schema": "vigproc.gridpool/1", "channels": ["R", "G", "B"], "info": self.info.tolist(),
                "weighted": self.weighted.tolist(), "n": self.n, "source": self.source}

    @classmethod
    def from_json(cls, d: Any) -> GridPool:
        """Inverse of :meth:`to_json`.

        Raises
        ------
        ModelError
            Not a grid pool, or malformed.
        """
        if not isinstance(d, dict) or d.get("schema") != "vigproc.gridpool/1" \
                or any(k not in d for k in ("info", "weighted", "n")):
            raise ModelError("a grid pool must be an object of schema 'vigproc.gridpool/1' with info, weighted and n")
        if d.get("channels", ["R", "G", "B"]) != ["R", "G", "B"]:
            raise ModelError("a grid pool's channels must be R, G, B")
        return cls(d["info"], d["weighted"], d["n"], str(d.get("source", "")))


# --------------------------------------------------------------------------- #
# the store's column
# --------------------------------------------------------------------------- #


def migration_grid(con: sqlite3.Connection) -> None:
    """v14: each profile's pooled grid field (:class:`GridPool`, JSON), NULL for none."""
    if "grid" not in {r[1] for r in con.execute("PRAGMA table_info(profiles)")}:
        con.execute("ALTER TABLE profiles ADD COLUMN grid TEXT")


def grid_to_column(pool: GridPool | None) -> str | None:
    return None if pool is None else json.dumps(pool.to_json(), separators=(",", ":"))


def grid_from_column(text: Any) -> GridPool | None:
    """Raises ValueError or ModelError for a damaged value."""
    return None if text is None else GridPool.from_json(json.loads(text))
