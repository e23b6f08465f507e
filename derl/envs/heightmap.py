"""Heightmap observation: terrain heights around many bodies at once, on a heading-aligned grid.

Paper, appendix B: a 2-D heightmap on a non-uniform grid, denser near the body, from ``behind``
(1 m) behind to ``ahead`` (4 m) ahead along the heading and ``side`` (4 m) to the left and right,
rotated with the yaw of the head, heights relative to the ground right under the head. As in the
original DERL (``HfieldObs2D``) the points are looked up directly in the height array (nearest
vertex, no ray casting); the default grid reproduces its 30 x 47 = 1410 points.

Lookup. The grid is anchored at the vertex nearest the head, and its offsets, rotated by each of
`YAW_BINS` evenly spaced yaws and rounded to whole cells, are precomputed as offsets of flat
indices (`offset_table`, once per `HeightStack`: about 20 ms). A lookup for N bodies is then: the
yaw bin and the head's vertex of each body (N numbers), one (N, K) gather from the table, an add,
one gather from the heights, and the height under the head, the grid's own point (0, 0),
subtracted: no per-point arithmetic. Heads whose whole grid lies on one height (a flat start
area) skip it: their heightmap is zeros. (Right after a physics step, reading 32 heads' grids
takes 0.1-0.3 ms, mostly cache misses.)

Accuracy. The yaw is rounded to the nearest bin (0.125 degree at most), which moves the
furthest point (5.7 m) by at most 1/8 of a cell, and the grid is anchored at the head's nearest
vertex instead of the head itself (up to half a cell along each axis). So a point may read a
vertex one cell (0.1 m) away, along each axis, from the vertex nearest its exact position, never
further. Over random positions and yaws about 57% of the points read exactly that vertex, and
about 97% read the vertex that an exact rotation about the head's vertex would. The original
truncated coordinates to whole cells, an error of the same order (it reads the nearest vertex
for only about a quarter of the points).

Edges. Heights are stored padded on every side by `HeightStack.margin` cells that repeat the edge
values, further than the grid reaches, so every point reads a vertex of its own terrain, and
points outside the world read the nearest edge vertex (the world continues flat at its edge
heights; in an environment the heightfield is padded the same way, so the physics agrees) instead of
the original's -10 m gap: it keeps observations in the terrain's own range, and episodes end
before bodies get there. A head outside the world counts as on its edge.
"""

from __future__ import annotations

import math
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike
from pydantic import BaseModel, ConfigDict, Field, model_validator

from derl.envs.terrain import Terrain

# 0.25 degree apart: the default grid's furthest point (5.7 m) moves at most 1/8 of a 0.1 m cell;
# under half a cell for any grid reaching less than 22 m.
YAW_BINS = 1440


class HeightmapGrid(BaseModel):
    """Body-frame sampling points of the heightmap; extents in meters.

    Each half-axis of extent L holds n = L / resolution cells. Its samples are the inverse CDF of
    an exponential, scaled so the last one lands on n, floored to whole cells and de-duplicated:

        cells_k = floor(n * ln(1 - k/n) / ln(1/n)),  k = 0 .. n-1

    so they are one cell apart near the body and ever sparser further out, ending exactly at L.
    The forward axis joins the negated ``behind`` half and the ``ahead`` half; the left axis joins
    two ``side`` halves. The defaults give 30 forward x 47 left offsets = 1410 points, the same
    as the original code (``_sample_non_uniform``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    behind: float = Field(1.0, ge=0)
    ahead: float = Field(4.0, gt=0)
    side: float = Field(4.0, gt=0)
    resolution: float = Field(0.1, gt=0)

    @model_validator(mode="after")
    def _whole_cells(self) -> HeightmapGrid:
        for name in ("behind", "ahead", "side"):
            cells = getattr(self, name) / self.resolution
            if abs(cells - round(cells)) > 1e-6 or round(cells) == 1:
                raise ValueError(f"{name} must be 0 or at least 2 whole cells of {self.resolution}")
        return self

    @cached_property
    def forward(self) -> np.ndarray:
        """Sorted forward offsets (m); negative is behind."""
        return _axis(self.behind, self.ahead, self.resolution)

    @cached_property
    def left(self) -> np.ndarray:
        """Sorted leftward offsets (m); negative is to the right."""
        return _axis(self.side, self.side, self.resolution)

    @property
    def nx(self) -> int:
        return self.forward.size

    @property
    def ny(self) -> int:
        return self.left.size

    @property
    def size(self) -> int:
        """K = nx * ny, the length of one observation."""
        return self.nx * self.ny

    @cached_property
    def reach(self) -> float:
        """Distance (m) from the body to the furthest point of the grid."""
        return float(np.hypot(self.offsets[:, 0], self.offsets[:, 1]).max())

    @cached_property
    def offsets(self) -> np.ndarray:
        """(K, 2) body-frame (forward, left) offsets in meters, ordered like an (ny, nx) image:
        k = iy * nx + ix, so ``obs.reshape(ny, nx)`` has rows = left offset, columns = forward."""
        forward, left = np.meshgrid(self.forward, self.left)
        return np.stack((forward.ravel(), left.ravel()), axis=1)


def offset_table(grid: HeightmapGrid, resolution: float, row_length: int) -> np.ndarray:
    """(YAW_BINS, K) int32 flat-index offsets of the grid's points, rotated by yaw
    ``2 pi b / YAW_BINS`` in row b, in a row-major height array of rows of ``row_length`` vertices
    ``resolution`` m apart: round(d_row) * row_length + round(d_col)."""
    yaw = np.arange(YAW_BINS) * (2 * np.pi / YAW_BINS)
    cos, sin = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    forward, left = grid.offsets.T / resolution
    d_col = np.rint(cos * forward - sin * left).astype(np.int32)
    d_row = np.rint(sin * forward + cos * left).astype(np.int32)
    return d_row * np.int32(row_length) + d_col


def padding(grid: HeightmapGrid | None, resolution: float) -> int:
    """Edge-valued cells a terrain needs on every side so that each point of ``grid`` around a
    head anywhere on the terrain reads a vertex of that terrain (0 without a heightmap)."""
    return 0 if grid is None else math.ceil(grid.reach / resolution) + 1


class HeightStack:
    """M terrains laid out like ``layout`` (its shape, resolution and extent) and the heightmap
    and ground lookups on them, all at once. The terrains are stacked in one float32 array of
    heights in metres, `padded` (M, nrow + 2 m, ncol + 2 m), m = `margin` = `padding` (grid):
    each terrain framed by m cells on every side that repeat its edges (`write`).

    Flat indices into the stack are int32 (numpy gathers them faster than int64), which limits a
    stack to 2**31 vertices: 1700 copies of a 100 m x 100 m terrain.

    A head whose grid lies on one height (a stretch of columns, each the same height from edge
    to edge, such as a flat start area) sees all zeros: its heightmap is not looked up, which
    saves the cache misses of reading its part of the stack (`rough` tells which columns need it).
    """

    def __init__(self, layout: Terrain, count: int, grid: HeightmapGrid | None) -> None:
        self.layout = layout
        self.margin = m = padding(grid, layout.resolution)
        nrow, ncol = layout.nrow, layout.ncol
        self.padded = np.zeros((count, nrow + 2 * m, ncol + 2 * m), np.float32)
        if self.padded.size > np.iinfo(np.int32).max:
            raise ValueError(f"{count} terrains of {layout.heights.shape} exceed 2**31 vertices")
        self.interior = self.padded[:, m : m + nrow, m : m + ncol]
        """The terrains' own vertices: a view of `padded` (`write` sets them and the padding)."""
        # (M, ncol) whether a head above the column reads more than one height (all zeros: no)
        self.rough = np.zeros((count, ncol), bool)
        row_length = self.padded.shape[2]
        self._flat = self.padded.reshape(-1)
        self._table = None if grid is None else offset_table(grid, layout.resolution, row_length)
        self._head = 0 if grid is None else grid.offsets.tolist().index([0.0, 0.0])
        first = np.arange(count) * self.padded[0].size + m * row_length + m
        self._first = first.astype(np.int32)  # flat index of each terrain's vertex (0, 0)
        self._terrains = np.arange(count)
        self._strides = np.array([1, row_length], np.int32)  # flat index step per column, row
        self._origin = np.array([layout.x_min, layout.y_min])
        self._divisions = 1.0 / layout.resolution  # cells per metre
        self._origin_cells = self._origin * self._divisions
        self._last = np.array([ncol - 1, nrow - 1])

    @property
    def heights(self) -> np.ndarray:
        """(M, nrow, ncol) the terrains without their padding (a read-only view: see `write`)."""
        view = self.interior.view()
        view.flags.writeable = False
        return view

    def write(self, i: int, heights: np.ndarray) -> None:
        """Terrain ``i`` becomes ``heights`` (nrow, ncol); its padding repeats its edges."""
        m, padded = self.margin, self.padded[i]
        nrow, ncol = self.layout.nrow, self.layout.ncol
        padded[m : m + nrow, m : m + ncol] = heights
        padded[:m, m : m + ncol] = heights[0]
        padded[m + nrow :, m : m + ncol] = heights[-1]
        padded[:, :m] = padded[:, m : m + 1]
        padded[:, m + ncol :] = padded[:, m + ncol - 1 : m + ncol]
        self.rough[i] = rough_columns(heights, m)

    def vertices(
        self, xy: np.ndarray, which: np.ndarray | None = None, floored: bool = False
    ) -> np.ndarray:
        """(N,) flat index in `padded` of the vertex nearest ``xy[n]`` (``floored``: at its
        position floored to whole cells, the corner of the cell it is in; clamped to the terrain)
        on terrain ``which[n]`` (default: terrain n)."""
        return self._vertices(self._cells(xy, floored), self._which(xy, which))

    def ground(
        self, xy: np.ndarray, which: np.ndarray | None = None, floored: bool = False
    ) -> np.ndarray:
        """(N,) height of the vertex nearest each point, as the heightmap reads it, in m;
        ``floored``: of the cell's corner, as the released code's fall test reads it."""
        return self._flat[self.vertices(xy, which, floored)].astype(np.float64)

    def top(self, xy: np.ndarray, half: float, which: np.ndarray | None = None) -> np.ndarray:
        """(N,) the highest vertex within ``half`` (m, rounded to whole cells) along each axis
        of the vertex nearest each point (the square clamped to the terrain), in m."""
        k = round(half / self.layout.resolution)
        cells = self._cells(xy)[:, :, None] + np.arange(-k, k + 1, dtype=np.int32)  # (N, 2, S)
        np.minimum(np.maximum(cells, 0, out=cells), self._last[:, None], out=cells)
        first = self._first[self._which(xy, which)][:, None, None]
        square = first + cells[:, 1, :, None] * self._strides[1] + cells[:, 0, None, :]  # N, S, S
        return self._flat[square].max(axis=(1, 2)).astype(np.float64)

    def heightmap(
        self, xy: np.ndarray, yaw: np.ndarray, which: np.ndarray | None = None
    ) -> np.ndarray:
        """(N, K) float32 heightmaps of heads at ``xy`` (N, 2) facing ``yaw`` (N,), head n on
        terrain ``which[n]`` (default: n), relative to the ground under each head. ``yaw`` is the
        angle of the head's x-axis projected on the ground, from world +x towards +y."""
        cells, terrains = self._cells(xy), self._which(xy, which)
        rough = np.flatnonzero(self.rough[terrains, cells[:, 0]])
        if len(rough) == len(xy):
            return self.lookup(self._vertices(cells, terrains), yaw)
        heights = np.zeros((len(xy), self._offsets.shape[1]), np.float32)
        if len(rough):
            centre = self._vertices(cells[rough], terrains[rough])
            heights[rough] = self.lookup(centre, yaw[rough])
        return heights

    @property
    def _offsets(self) -> np.ndarray:
        """The offset table (`offset_table`): a stack made without a grid has no heightmaps."""
        assert self._table is not None, "a HeightStack made without a grid has no heightmaps"
        return self._table

    def lookup(self, centre: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        """(N, K) float32 heightmaps around the vertices ``centre`` (N,) (flat indices) facing
        ``yaw`` (N,), relative to those vertices: the stack read at every point of the grid."""
        bins = np.rint(yaw * (YAW_BINS / (2 * np.pi))).astype(np.intp)
        index = self._offsets.take(bins, axis=0, mode="wrap")
        index += centre[:, None]
        heights = self._flat.take(index)
        heights -= heights[:, self._head, None]  # the head's own vertex: offset (0, 0)
        return heights

    def _cells(self, xy: np.ndarray, floored: bool = False) -> np.ndarray:
        """(N, 2) int32 (column, row) of the vertex nearest each point (``floored``: at the
        point's position floored to whole cells, as the released code's `Terrain.pos_to_idx`
        computes it, floor(x * divisions): x / resolution can fall an ulp short of a whole
        number), clamped to the terrain."""
        if floored:
            cells = xy * self._divisions
            cells -= self._origin_cells
        else:
            cells = (xy - self._origin) / self.layout.resolution
        np.minimum(np.maximum(cells, 0.0, out=cells), self._last, out=cells)  # clip, as ufuncs
        if not floored:
            cells += 0.5
        return cells.astype(np.int32)

    def _which(self, xy: np.ndarray, which: np.ndarray | None) -> np.ndarray:
        return self._terrains[: len(xy)] if which is None else which

    def _vertices(self, cells: np.ndarray, terrains: np.ndarray) -> np.ndarray:
        return self._first[terrains] + cells @ self._strides


def rough_columns(heights: np.ndarray, reach: int) -> np.ndarray:
    """(ncol,) bool: whether columns ``c - reach .. c + reach`` of ``heights`` (clamped to the
    array) hold more than one height, for each column c; repeated edges add no new height."""
    level = (heights == heights[0]).all(axis=0)  # each column one height
    same = level[:-1] & level[1:] & (heights[0, :-1] == heights[0, 1:])  # columns c, c + 1
    return spread(~same, reach)


def spread(changes: np.ndarray, reach: int) -> np.ndarray:
    """(ncol,) bool from (ncol - 1,) bool ``changes`` (columns c and c + 1 are not both level
    at one height): whether a change lies within columns ``c - reach .. c + reach`` (clamped)."""
    count = np.concatenate(([0], np.cumsum(changes)))  # count[c]: changes before column c
    column = np.arange(len(count))
    low, high = np.maximum(column - reach, 0), np.minimum(column + reach, len(count) - 1)
    return count[high] > count[low]


def sample(terrain: Terrain, xy: ArrayLike, yaw: ArrayLike, grid: HeightmapGrid) -> np.ndarray:
    """Heightmaps (N, K) float32 of N bodies on one terrain, heads at ``xy`` (N, 2) facing
    ``yaw`` (N,); see `HeightStack.heightmap`. The entry at offset (0, 0) is always 0. For one-off
    lookups: it builds the yaw tables (~20 ms) on every call; environments keep a `HeightStack`."""
    xy = np.asarray(xy, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or yaw.shape != (xy.shape[0],):
        raise ValueError(f"need xy (N, 2) and yaw (N,), got {xy.shape} and {yaw.shape}")
    stack = HeightStack(terrain, 1, grid)
    stack.write(0, terrain.heights)
    return stack.heightmap(xy, yaw, np.zeros(len(xy), dtype=np.intp))


def _axis(low: float, high: float, resolution: float) -> np.ndarray:
    """Offsets (m) from -low to +high, dense near 0."""
    below = -_half_axis(round(low / resolution)) if low > 0 else np.zeros(1, dtype=np.intp)
    return np.union1d(below, _half_axis(round(high / resolution))) * resolution


def _half_axis(n: int) -> np.ndarray:
    """Whole-cell offsets 0..n, one apart near 0 and sparser outwards (formula in HeightmapGrid)."""
    spread = -np.log(1.0 - np.arange(n) / n)
    return np.unique((spread / spread[-1] * n).astype(np.intp))
