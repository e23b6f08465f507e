"""Procedural terrain as a height array, laid out the way MuJoCo height fields store it.

A world is a corridor along +x built the way the released DERL code builds it (its
``derl/envs/modules/terrain.py`` with ``configs/evo/vt.yml`` and ``mvt.yml``): a flat start area
centred on the spawn point, then, until the corridor's far end, a flat segment followed by an
obstacle drawn uniformly among hills, steps and rubble, each spanning the whole width in y. Every
length and height is drawn uniformly from a finite set (the released ``[start, stop, step]``
ranges of half-lengths, stop included): flats 2, 4 or 6 m, hills and rubble 8 or 16 m, steps 24
or 32 m. An obstacle that does not fit in what is left of the corridor is skipped and the loop
goes on with another flat and another draw; the flat that reaches the far end is cut there.

Heights live on a regular grid of vertices, row index = y and column index = x, centred at the
world origin: vertex (r, c) is at x = -size_x/2 + c*res, y = -size_y/2 + r*res. This is exactly
the vertex layout of a MuJoCo hfield of size (size_x/2, size_y/2, max_height, base) with
nrow x ncol = heights.shape, placed at the origin. An obstacle of n cells sets n columns of
vertices, as the released code sets n columns of its height array. The elevation scale
``max_height`` is fixed per world (compiled into the model), so a new terrain of the same shape
can be written into ``model.hfield_data`` in place without recompiling.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Annotated, Literal, NamedTuple, TypeVar

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

ObstacleKind = Literal["hills", "steps", "rubble"]
SegmentKind = Literal["flat", "hills", "steps", "rubble", "boxes"]
Range = tuple[float, float]
T = TypeVar("T")


def _positive(values: tuple[float, ...]) -> tuple[float, ...]:
    if not values or min(values) <= 0:
        raise ValueError(f"choices must be a non-empty set of positive values, got {values}")
    return values


# A draw uniform over these values (the released code's `sample_from_range`)
Choices = Annotated[tuple[float, ...], AfterValidator(_positive)]
Counts = Annotated[tuple[int, ...], AfterValidator(_positive)]


class TerrainConfig(BaseModel):
    """Parameters of the terrain generator; lengths and heights in meters, full lengths (the
    released config gives half-lengths). Defaults are the released VT values; ``obstacles=()``
    gives an all-flat world.

    Hills are H sin(0..pi) along x over the obstacle, H from ``hill_height``. Steps are
    ``num_steps`` treads of equal length at heights 0, h, 2h, 3h, 3h, 2h, h, 0 for 8 steps of h:
    up and back down, the top one doubled. Rubble is strips along x stacked across the
    corridor, each ``rubble_strip_width`` wide, each a triangle wave of peak ``rubble_peak``
    along x with ``rubble_half_periods`` half-periods over the obstacle, clipped at
    ``rubble_clip``; every strip draws its own width, half-periods and clip.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    size_x: float = Field(100.0, gt=0)
    size_y: float = Field(100.0, gt=0)
    resolution: float = Field(0.1, gt=0)
    max_height: float = Field(1.5, gt=0)
    start_flat: float = Field(6.0, ge=0)  # START_FLAT 3; the spawn point is its middle
    flat_length: Choices = (2.0, 4.0, 6.0)  # FLAT_LENGTH_RANGE [1, 3, 1]
    obstacle_length: Choices = (8.0, 16.0)  # HFIELD_LENGTH_RANGE [4, 8, 4]: hills and rubble
    steps_length: Choices = (24.0, 32.0)  # STEP_LENGTH_RANGE [12, 16, 4]
    obstacles: tuple[ObstacleKind, ...] = ("hills", "steps", "rubble")
    hill_height: Choices = (0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2)  # CURVE_HEIGHT_RANGE
    num_steps: int = Field(8, ge=4)
    step_height: float = Field(0.2, gt=0)
    # range(10, 20) rows of the released 0.1 m grid
    rubble_strip_width: Choices = (1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6, 1.7, 1.8, 1.9)
    rubble_half_periods: Counts = (10, 15)
    rubble_clip: Choices = (0.2, 0.3)  # RUGGED_SQUARE_CLIP_RANGE [0.2, 0.3, 0.1]
    rubble_peak: float = Field(2.0, gt=0)  # scipy.signal.sawtooth(t, 0.5) + 1

    @model_validator(mode="after")
    def _consistent(self) -> TerrainConfig:
        lengths = {
            "size_x": (self.size_x,),
            "size_y": (self.size_y,),
            "start_flat": (self.start_flat,),
            "flat_length": self.flat_length,
            "obstacle_length": self.obstacle_length,
            "steps_length": self.steps_length,
            "rubble_strip_width": self.rubble_strip_width,
        }
        for name, values in lengths.items():
            for value in values:
                cells = value / self.resolution
                if abs(cells - round(cells)) > 1e-6:
                    raise ValueError(f"{name} must be multiples of resolution {self.resolution}")
        if self.start_flat >= self.size_x:
            raise ValueError("start_flat must be shorter than size_x")
        if self.num_steps % 2:
            raise ValueError("num_steps must be even (half up, half down)")
        if any(_cells(length, self.resolution) % self.num_steps for length in self.steps_length):
            raise ValueError("steps_length must be whole numbers of cells per tread")
        tops = {
            "hills": max(self.hill_height),
            "steps": self.steps_top,
            "rubble": max(self.rubble_clip),
        }
        for kind in self.obstacles:
            if tops[kind] > self.max_height:
                raise ValueError(f"{kind} reach {tops[kind]} m > max_height {self.max_height} m")
        if self.rubble_peak <= max(self.rubble_clip):
            raise ValueError("rubble_peak must exceed rubble_clip so every strip is clipped")
        return self

    @property
    def steps_top(self) -> float:
        """Height of the highest tread of a step obstacle."""
        return self.step_height * (self.num_steps // 2 - 1)

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
        """VT: 100 x 100 m of hills, steps and rubble (released SIZE [50, 50])."""
        return cls(**{"size_x": 100.0, "size_y": 100.0, **overrides})

    @classmethod
    def manipulation(cls, **overrides: object) -> TerrainConfig:
        """MVT: 60 x 40 m with the VT obstacles (released SIZE [30, 20])."""
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

    def hfield(self, base: float = 0.1) -> HField:
        """The MuJoCo hfield description of this terrain; ``base`` is the depth of the solid
        below z = 0. The hfield geom must sit at the origin with identity orientation."""
        data = self._normalized(np.empty(self.heights.size, np.float32))
        return HField((*self._extent, base), self.nrow, self.ncol, data)

    @property
    def _extent(self) -> tuple[float, float, float]:
        """The hfield's size[:3]: (radius_x, radius_y, elevation_z)."""
        return self.size_x / 2, self.size_y / 2, self.max_height

    def _normalized(self, out: np.ndarray) -> np.ndarray:
        """``out`` (float32, nrow * ncol) := heights / max_height in [0, 1], flattened."""
        np.divide(self.heights.ravel(), np.float32(self.max_height), out=out)
        return np.clip(out, 0.0, 1.0, out=out)


class Span(NamedTuple):
    """A stretch of a drawn corridor, before its heights are written (`render`): vertex columns
    [c0, c1) of ``kind``, designed top ``top`` (m, as `Segment`), row r's heights along x
    ``profiles[pick[r]]`` (float32, m; ``pick`` None: ``profiles[0]`` in every row)."""

    kind: SegmentKind
    c0: int
    c1: int
    top: float
    pick: np.ndarray | None
    profiles: np.ndarray


def generate_terrain(config: TerrainConfig, rng: np.random.Generator) -> Terrain:
    """Draw a new world from ``config``; deterministic for a given generator state."""
    heights = np.empty(config.grid_shape, dtype=np.float32)
    spans = plan_terrain(config, rng)
    render(spans, heights, (0, heights.shape[0]), (0, heights.shape[1]))
    x_min, res = -config.size_x / 2, config.resolution
    segments = [
        Segment(s.kind, round(x_min + s.c0 * res, 9), round(x_min + s.c1 * res, 9), s.top)
        for s in spans
    ]
    return Terrain(
        heights=heights,
        resolution=res,
        max_height=config.max_height,
        spawn=(x_min + config.start_flat / 2, 0.0),
        segments=tuple(segments),
    )


def plan_terrain(config: TerrainConfig, rng: np.random.Generator) -> list[Span]:
    """Every draw of a new world from ``config`` (those of `generate_terrain`), its heights not
    yet written: a few hundred numbers, whatever the world's size."""
    nrow, ncol = config.grid_shape
    spans = []
    for kind, c0, c1 in _layout(config, ncol - 1, rng):
        if kind == "flat":
            spans.append(Span(kind, c0, c1, 0.0, None, _level(c1 - c0)))
        elif kind == "rubble":
            spans.append(Span(kind, c0, c1, *_rubble(c1 - c0, nrow, config, rng)))
        else:
            top, profile = _BUILDERS[kind](c1 - c0, config, rng)
            spans.append(Span(kind, c0, c1, top, None, profile[None]))
    return spans


def render(
    spans: list[Span],
    out: np.ndarray,
    rows: tuple[int, int],
    cols: tuple[int, int],
    margin: int = 0,
) -> None:
    """Write rows [rows) and columns [cols) (indices of ``out``) of the world ``spans`` plans
    into ``out``, a float32 array of its vertices framed by ``margin`` cells on every side that
    repeat its edges, (nrow + 2 margin, ncol + 2 margin). Columns beyond the last span (the far
    edge's) are flat."""
    (r0, r1), (c0, c1) = rows, cols
    block = out[r0:r1, c0:c1]
    nrow, ncol = out.shape[0] - 2 * margin, out.shape[1] - 2 * margin
    first, last = (min(max(c - margin, 0), ncol - 1) for c in (c0, c1 - 1))  # terrain columns
    terrain_rows = None  # of the block's rows (the frame repeats the edge rows)
    for span in spans:
        if span.c1 <= first:
            continue
        if span.c0 > last:
            break
        # the block's columns of the span (the frame's left part repeats the first column)
        lo = 0 if span.c0 == 0 else max(span.c0 + margin - c0, 0)
        hi = min(span.c1 + margin - c0, c1 - c0)
        along = c0 + lo - margin - span.c0  # the span's column at the block's column lo
        if along >= 0:
            profiles = span.profiles[:, along : along + hi - lo]
        else:
            profiles = span.profiles[:, np.maximum(np.arange(along, along + hi - lo), 0)]
        if span.pick is None:
            block[:, lo:hi] = profiles[0]
            continue
        if terrain_rows is None:
            terrain_rows = np.clip(np.arange(r0, r1) - margin, 0, nrow - 1)
        block[:, lo:hi] = profiles[span.pick[terrain_rows]]
    block[:, max(spans[-1].c1 + margin - c0, 0) :] = 0.0


def _cells(length: float, resolution: float) -> int:
    return round(length / resolution)


def _pick(values: tuple[T, ...], rng: np.random.Generator) -> T:
    """One of ``values``, uniformly (`Generator.random`: a fifth of `Generator.integers`' cost)."""
    return values[int(rng.random() * len(values))]


def _layout(
    config: TerrainConfig, end: int, rng: np.random.Generator
) -> list[tuple[SegmentKind, int, int]]:
    """Column spans [c0, c1) over the ``end`` cells of the corridor: the start area, then while
    the corridor goes on a flat (cut at the end) and an obstacle if it fits before the end."""
    res = config.resolution
    if not config.obstacles:
        return [("flat", 0, end)]
    col = _cells(config.start_flat, res)
    spans: list[tuple[SegmentKind, int, int]] = [("flat", 0, col)]
    while col < end:
        kind = _pick(config.obstacles, rng)
        n_flat = min(_cells(_pick(config.flat_length, rng), res), end - col)
        spans.append(("flat", col, col + n_flat))
        col += n_flat
        lengths = config.steps_length if kind == "steps" else config.obstacle_length
        n_obstacle = _cells(_pick(lengths, rng), res)
        if col + n_obstacle <= end:
            spans.append((kind, col, col + n_obstacle))
            col += n_obstacle
    return spans


def _hills(n: int, config: TerrainConfig, rng: np.random.Generator) -> tuple[float, np.ndarray]:
    """H sin over n columns from 0 to pi, both ends included (0 at both), constant across y."""
    height = _pick(config.hill_height, rng)
    return height, (height * _half_sine(n)).astype(np.float32)


def _steps(n: int, config: TerrainConfig, rng: np.random.Generator) -> tuple[float, np.ndarray]:
    """num_steps treads of n / num_steps columns each at 0, h, ..., top, top, ..., h, 0."""
    return config.steps_top, _stairs(n, config.num_steps, config.step_height)


# The profiles below depend on a span's length and the configuration only: computed once each
# (plans are drawn at every reset), and read-only.


@functools.cache
def _level(n: int) -> np.ndarray:
    return _frozen(np.zeros((1, n), np.float32))


@functools.cache
def _half_sine(n: int) -> np.ndarray:
    return _frozen(np.sin(np.linspace(0.0, np.pi, n)))


@functools.cache
def _stairs(n: int, num_steps: int, step_height: float) -> np.ndarray:
    tread = np.arange(num_steps)
    levels = step_height * np.minimum(tread, num_steps - 1 - tread)
    return _frozen(np.repeat(levels, n // num_steps).astype(np.float32))


@functools.cache
def _clipped_waves(
    n: int, half_periods: tuple[int, ...], clips: tuple[float, ...], peak: float
) -> np.ndarray:
    """(len(half_periods) * len(clips), n): each pair's profile, clips varying fastest."""
    # Position in the wave, in half-periods modulo a period: linspace(0, f, n) % 2 for each f.
    phase = np.outer(half_periods, np.arange(n) / (n - 1)) % 2.0
    waves = peak * (1.0 - np.abs(phase - 1.0))
    profiles = np.minimum(waves[:, None, :], np.array(clips)[:, None]).reshape(-1, n)
    return _frozen(profiles.astype(np.float32))


@functools.cache
def _strip_widths(widths: tuple[float, ...], resolution: float) -> np.ndarray:
    return _frozen(np.array([_cells(w, resolution) for w in widths]))


def _frozen(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def _rubble_strips(
    nrow: int, config: TerrainConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rubble's draws for a block of ``nrow`` rows: each strip's rows, and the indices of its
    half-periods and clip height in the config's choices; strips are stacked from row 0 until
    they cover the block (the last one is cut)."""
    widths = _strip_widths(config.rubble_strip_width, config.resolution)
    draws = rng.random((3, -(-nrow // widths.min())))  # enough strips
    rows = widths[(draws[0] * len(widths)).astype(np.intp)]
    count = int(np.searchsorted(np.cumsum(rows), nrow)) + 1
    wave = (draws[1, :count] * len(config.rubble_half_periods)).astype(np.intp)
    clip = (draws[2, :count] * len(config.rubble_clip)).astype(np.intp)
    return rows[:count], wave, clip


def _rubble(
    n: int, nrow: int, config: TerrainConfig, rng: np.random.Generator
) -> tuple[float, np.ndarray, np.ndarray]:
    """Strips along x, each min(triangle wave, clip) with the wave 0 -> peak -> 0 over two
    half-periods (``sawtooth(linspace(0, f pi, n), 0.5) + 1`` for peak 2): the top, each row's
    profile, and the profiles (one per pair of half-periods and clip)."""
    rows, wave, clip = _rubble_strips(nrow, config, rng)
    clips = config.rubble_clip
    profiles = _clipped_waves(n, config.rubble_half_periods, clips, config.rubble_peak)
    top = max(clips[k] for k in set(clip.tolist()))
    return top, np.repeat(wave * len(clips) + clip, rows)[:nrow], profiles


_BUILDERS = {"hills": _hills, "steps": _steps}
