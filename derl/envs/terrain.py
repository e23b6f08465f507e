"""Procedural terrain as a height array, laid out the way MuJoCo height fields store it.

A world is a corridor along +x (paper, appendix A): a flat start area around the spawn point,
then flat segments of length U[1, 3] m interleaved with obstacle segments of length U[4, 8] m,
each obstacle drawn uniformly among hills, steps and rubble and spanning the whole width in y.

Heights live on a regular grid of vertices, row index = y and column index = x, centred at the
world origin: vertex (r, c) is at x = -size_x/2 + c*res, y = -size_y/2 + r*res. This is exactly
the vertex layout of a MuJoCo hfield of size (size_x/2, size_y/2, max_height, base) with
nrow x ncol = heights.shape, placed at the origin. The elevation scale ``max_height`` is fixed
per world (compiled into the model), so a new terrain of the same shape can be written into
``model.hfield_data`` in place without recompiling.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

if TYPE_CHECKING:
    import mujoco

ObstacleKind = Literal["hills", "steps", "rubble"]
SegmentKind = Literal["flat", "hills", "steps", "rubble", "boxes"]
Range = tuple[float, float]


class TerrainConfig(BaseModel):
    """Parameters of the terrain generator; lengths and heights in meters.

    Defaults are the paper's VT ranges. ``obstacles=()`` gives an all-flat world. Rubble is a grid
    of pyramids (a triangle wave in x times one in y, combined with ``min``) of peak
    ``rubble_peak``, each pyramid clipped at its own height U[rubble_clip]; pyramid footprints are
    U[rubble_bump] m per obstacle, rounded so a whole number fits the obstacle length and width.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    size_x: float = Field(100.0, gt=0)
    size_y: float = Field(100.0, gt=0)
    resolution: float = Field(0.1, gt=0)
    max_height: float = Field(1.5, gt=0)
    # A body at the spawn point (the middle of the start area) perceives only flat ground: its
    # heightmap reaches 5.7 m, the first obstacle is at least 7 + 1 m away.
    start_flat: float = Field(14.0, ge=0)
    flat_length: Range = (1.0, 3.0)
    obstacle_length: Range = (4.0, 8.0)
    obstacles: tuple[ObstacleKind, ...] = ("hills", "steps", "rubble")
    hill_amplitude: Range = (0.6, 1.2)
    num_steps: int = Field(8, gt=0)
    step_height: float = Field(0.2, gt=0)
    rubble_clip: Range = (0.2, 0.3)
    rubble_peak: float = Field(0.5, gt=0)
    rubble_bump: Range = (0.8, 1.6)

    @field_validator(
        "flat_length", "obstacle_length", "hill_amplitude", "rubble_clip", "rubble_bump"
    )
    @classmethod
    def _positive_range(cls, value: Range) -> Range:
        if not 0 < value[0] <= value[1]:
            raise ValueError(f"range must satisfy 0 < low <= high, got {value}")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> TerrainConfig:
        for name in ("size_x", "size_y", "start_flat"):
            cells = getattr(self, name) / self.resolution
            if abs(cells - round(cells)) > 1e-6:
                raise ValueError(f"{name} must be a multiple of resolution {self.resolution}")
        if self.start_flat >= self.size_x:
            raise ValueError("start_flat must be shorter than size_x")
        if self.num_steps % 2:
            raise ValueError("num_steps must be even (half up, half down)")
        tops = {
            "hills": self.hill_amplitude[1],
            "steps": self.steps_top,
            "rubble": self.rubble_clip[1],
        }
        for kind in self.obstacles:
            if tops[kind] > self.max_height:
                raise ValueError(f"{kind} reach {tops[kind]} m > max_height {self.max_height} m")
        if self.rubble_peak <= self.rubble_clip[1]:
            raise ValueError("rubble_peak must exceed rubble_clip so every bump is clipped")
        return self

    @property
    def steps_top(self) -> float:
        """Height of the highest tread of a step obstacle."""
        return self.step_height * (self.num_steps // 2)

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(nrow, ncol) of the vertex grid."""
        return _cells(self.size_y, self.resolution) + 1, _cells(self.size_x, self.resolution) + 1

    @classmethod
    def flat(cls, **overrides: object) -> TerrainConfig:
        """FT: 150 x 150 m, all flat (a plane would do; a Terrain keeps the code uniform)."""
        return cls(**{"size_x": 150.0, "size_y": 150.0, "obstacles": (), **overrides})

    @classmethod
    def variable(cls, **overrides: object) -> TerrainConfig:
        """VT: 100 x 100 m of hills, steps and rubble."""
        return cls(**{"size_x": 100.0, "size_y": 100.0, **overrides})

    @classmethod
    def manipulation(cls, **overrides: object) -> TerrainConfig:
        """MVT: 60 x 40 m with the VT obstacles."""
        return cls(**{"size_x": 60.0, "size_y": 40.0, **overrides})


@dataclass(frozen=True)
class Segment:
    """A stretch of the corridor along x. ``height`` is the obstacle's designed top (hill
    amplitude, top tread, highest rubble clip); 0 for flat segments."""

    kind: SegmentKind
    x_start: float
    x_end: float
    height: float

    @property
    def length(self) -> float:
        return self.x_end - self.x_start


class HField(NamedTuple):
    """What a MuJoCo hfield needs: ``size`` = (radius_x, radius_y, elevation_z, base_z) and
    ``data`` = heights / elevation_z in [0, 1], flattened row-major (``model.hfield_data``)."""

    size: tuple[float, float, float, float]
    nrow: int
    ncol: int
    data: np.ndarray


@dataclass(frozen=True, eq=False)
class Terrain:
    """Heights (float32, meters, shape (nrow, ncol), row = y, column = x) of a world centred at
    the origin, with ``resolution`` meters between vertices. ``max_height`` is the hfield
    elevation scale; all heights lie in [0, max_height]. ``spawn`` is the (x, y) of the middle
    of the flat start area."""

    heights: np.ndarray
    resolution: float = 0.1
    max_height: float = 1.5
    spawn: tuple[float, float] = (0.0, 0.0)
    segments: tuple[Segment, ...] = ()

    def __post_init__(self) -> None:
        heights = np.ascontiguousarray(self.heights, dtype=np.float32)
        if heights.ndim != 2 or min(heights.shape) < 2:
            raise ValueError(f"heights must be 2-D with at least 2 x 2 vertices: {heights.shape}")
        if self.resolution <= 0 or self.max_height <= 0:
            raise ValueError("resolution and max_height must be positive")
        if heights.min() < 0 or heights.max() > self.max_height:
            raise ValueError(f"heights must lie in [0, max_height={self.max_height}]")
        object.__setattr__(self, "heights", heights)

    @property
    def nrow(self) -> int:
        return self.heights.shape[0]

    @property
    def ncol(self) -> int:
        return self.heights.shape[1]

    @property
    def size_x(self) -> float:
        return (self.ncol - 1) * self.resolution

    @property
    def size_y(self) -> float:
        return (self.nrow - 1) * self.resolution

    @property
    def x_min(self) -> float:
        return -self.size_x / 2

    @property
    def y_min(self) -> float:
        return -self.size_y / 2

    @property
    def first_obstacle(self) -> float:
        """x where the first non-flat segment starts: inf if all flat, -inf if the terrain has
        no segment layout (obstacles may be anywhere)."""
        if not self.segments:
            return -np.inf
        return min((s.x_start for s in self.segments if s.kind != "flat"), default=np.inf)

    def height_at(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Ground height at world (x, y), vectorised over broadcastable arrays.

        Interpolation is piecewise linear on MuJoCo's own triangulation of the hfield: each cell
        is split along the diagonal from vertex (r, c) to (r+1, c+1), so this is the surface that
        MuJoCo's collision and ``mj_ray`` see (exact up to float32). Points outside the grid read
        the height of the nearest edge (MuJoCo has no ground there).
        """
        u = np.clip((np.asarray(x, dtype=np.float64) - self.x_min) / self.resolution, 0, None)
        v = np.clip((np.asarray(y, dtype=np.float64) - self.y_min) / self.resolution, 0, None)
        u, v = np.minimum(u, self.ncol - 1), np.minimum(v, self.nrow - 1)
        c = np.minimum(u.astype(np.intp), self.ncol - 2)
        r = np.minimum(v.astype(np.intp), self.nrow - 2)
        fu, fv = u - c, v - r
        h = self.heights
        h00, h11 = h[r, c], h[r + 1, c + 1]
        # Lower triangle (fu >= fv) has its third vertex at (r, c+1), the upper one at (r+1, c).
        side = np.where(fu >= fv, h[r, c + 1], h[r + 1, c])
        big, small = np.maximum(fu, fv), np.minimum(fu, fv)
        return h00 + big * (side - h00) + small * (h11 - side)

    def hfield(self, base: float = 0.1) -> HField:
        """The MuJoCo hfield description of this terrain; ``base`` is the depth of the solid
        below z = 0. The hfield geom must sit at the origin with identity orientation."""
        data = self._normalized(np.empty(self.heights.size, np.float32))
        return HField((*self._extent, base), self.nrow, self.ncol, data)

    def write_to(self, model: mujoco.MjModel, hfield_id: int = 0) -> None:
        """Write this terrain into hfield ``hfield_id`` of a compiled model, in place.

        The hfield must have this terrain's nrow, ncol and size[:3]. Physics and ``mj_ray`` see
        the change at once; a renderer needs ``mujoco.mjr_uploadHField`` to show it.
        """
        shape = (int(model.hfield_nrow[hfield_id]), int(model.hfield_ncol[hfield_id]))
        if shape != self.heights.shape or not np.allclose(
            model.hfield_size[hfield_id, :3], self._extent
        ):
            raise ValueError(
                f"hfield {hfield_id} is {shape} of size {model.hfield_size[hfield_id]}, "
                f"terrain needs {self.heights.shape} of size {self._extent}"
            )
        adr = int(model.hfield_adr[hfield_id])
        self._normalized(model.hfield_data[adr : adr + self.heights.size])

    @property
    def _extent(self) -> tuple[float, float, float]:
        """The hfield's size[:3]: (radius_x, radius_y, elevation_z)."""
        return self.size_x / 2, self.size_y / 2, self.max_height

    def _normalized(self, out: np.ndarray) -> np.ndarray:
        """``out`` (float32, nrow * ncol) := heights / max_height in [0, 1], flattened."""
        np.divide(self.heights.ravel(), np.float32(self.max_height), out=out)
        return np.clip(out, 0.0, 1.0, out=out)


def generate_terrain(config: TerrainConfig, rng: np.random.Generator) -> Terrain:
    """Draw a new world from ``config``; deterministic for a given generator state."""
    heights = np.zeros(config.grid_shape, dtype=np.float32)
    ncol = heights.shape[1]
    x_min, res = -config.size_x / 2, config.resolution
    segments = []
    for kind, c0, c1 in _layout(config, ncol, rng):
        top = 0.0 if kind == "flat" else _BUILDERS[kind](heights[:, c0:c1], config, rng)
        x_start, x_end = (round(x_min + c * res, 9) for c in (c0, min(c1, ncol - 1)))
        segments.append(Segment(kind, x_start, x_end, top))
    return Terrain(
        heights=heights,
        resolution=res,
        max_height=config.max_height,
        spawn=(x_min + config.start_flat / 2, 0.0),
        segments=tuple(segments),
    )


def _cells(length: float, resolution: float) -> int:
    return round(length / resolution)


def _layout(
    config: TerrainConfig, ncol: int, rng: np.random.Generator
) -> list[tuple[SegmentKind, int, int]]:
    """Column spans [c0, c1): start area, then (flat, obstacle) pairs while an obstacle fits,
    then a flat tail up to the end of the world."""
    if not config.obstacles:
        return [("flat", 0, ncol)]
    col = _cells(config.start_flat, config.resolution)
    spans: list[tuple[SegmentKind, int, int]] = [("flat", 0, col)]
    while True:
        n_flat = _cells(rng.uniform(*config.flat_length), config.resolution)
        n_obstacle = _cells(rng.uniform(*config.obstacle_length), config.resolution)
        kind = config.obstacles[rng.integers(len(config.obstacles))]
        if col + n_flat + n_obstacle >= ncol:
            break
        spans += [("flat", col, col + n_flat), (kind, col + n_flat, col + n_flat + n_obstacle)]
        col += n_flat + n_obstacle
    spans.append(("flat", col, ncol))
    return spans


def _hills(block: np.ndarray, config: TerrainConfig, rng: np.random.Generator) -> float:
    """One sin(0..pi) bump along x of amplitude U[hill_amplitude], constant across y."""
    amplitude = rng.uniform(*config.hill_amplitude)
    n = block.shape[1]
    block[:] = amplitude * np.sin(np.pi * np.arange(n) / n)
    return amplitude


def _steps(block: np.ndarray, config: TerrainConfig, rng: np.random.Generator) -> float:
    """num_steps treads of equal length: half going up by step_height, half coming down."""
    n = block.shape[1]
    tread = np.arange(n) * config.num_steps // n
    block[:] = config.step_height * np.minimum(tread + 1, config.num_steps - tread)
    return config.steps_top


def _rubble_layout(
    shape: tuple[int, ...], config: TerrainConfig, rng: np.random.Generator
) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Rubble's draws for a (nrow, n) block: the bumps' clip heights (bumps_y, bumps_x), and
    along x and along y each vertex's bump and its rise within it (`_triangle`)."""
    nrow, n = shape
    bumps_x = max(1, round(n * config.resolution / rng.uniform(*config.rubble_bump)))
    bumps_y = max(1, round((nrow - 1) * config.resolution / rng.uniform(*config.rubble_bump)))
    clip = rng.uniform(*config.rubble_clip, size=(bumps_y, bumps_x))
    along_x = _triangle(np.arange(n) * (bumps_x / n), bumps_x)
    along_y = _triangle(np.arange(nrow) * (bumps_y / (nrow - 1)), bumps_y)
    return clip, along_x, along_y


def _rubble(block: np.ndarray, config: TerrainConfig, rng: np.random.Generator) -> float:
    """A grid of pyramids over x and y, each clipped at its own height U[rubble_clip]."""
    clip, (ix, tx), (iy, ty) = _rubble_layout(block.shape, config, rng)
    # min(peak * min(ty, tx), clip) computed in float32: scaling by peak and rounding to float32
    # preserve order, so this is the float64 result rounded, with less memory traffic
    rows = (config.rubble_peak * ty).astype(np.float32)
    columns = (config.rubble_peak * tx).astype(np.float32)
    np.minimum(rows[:, None], columns, out=block)
    np.minimum(block, clip.astype(np.float32)[:, ix][iy], out=block)
    return float(clip.max())


def _triangle(phase: np.ndarray, periods: int) -> tuple[np.ndarray, np.ndarray]:
    """Period index of each phase in [0, periods] and a triangle wave 0 -> 1 -> 0 per period."""
    index = np.minimum(phase.astype(np.intp), periods - 1)
    return index, np.maximum(1.0 - np.abs(2.0 * (phase - index) - 1.0), 0.0)


_BUILDERS = {"hills": _hills, "steps": _steps, "rubble": _rubble}
