"""Arenas: the ground of a task. `Floor` is a plane, level or tilted; `Heightfield` gives every
copy its own terrain, drawn anew for every episode (VT's corridor by default, or the obstacle
boxes and the escape bowl defined here)."""

from __future__ import annotations

from collections.abc import Callable
from functools import cached_property

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from derl.envs.flat_ground import FlatGround, add_plane
from derl.envs.heightmap import HeightmapGrid
from derl.envs.task import Arena
from derl.envs.terrain import Segment, Terrain, TerrainConfig
from derl.envs.terrain_stack import TerrainStack, add_hfield
from derl.envs.view import MAX_SPEED, EnvView
from derl.unimal.space import HEAD_RADIUS, LIMB_LENGTHS, LIMB_RADIUS, MAX_LIMBS

DIVISIONS = 10
"""Cells per metre of the released code's terrain grid (`HFIELD.NUM_DIVS`), whose cells its fall
test reads on the slopes too."""
BODY_REACH = HEAD_RADIUS + MAX_LIMBS * max(LIMB_LENGTHS) + LIMB_RADIUS
"""m: no point of a body is further than this from its head's centre (a chain of the longest
limbs)."""


class Floor(Arena):
    """A ``length`` x ``width`` plane, tilted ``slope`` degrees about y so that +x goes uphill;
    ``half`` is its footprint on the ground plane."""

    def __init__(self, length: float, width: float, slope: float = 0.0) -> None:
        self.length, self.width = length, width
        self.slope = slope
        self.angle = np.deg2rad(slope)
        self.tilt = (np.cos(self.angle / 2), 0.0, -np.sin(self.angle / 2), 0.0)
        self.cos_slope = np.cos(self.angle)
        self.tan_slope = np.tan(self.angle)
        self.half = (length / 2 * self.cos_slope, width / 2)

    def build(self, spec: mujoco.MjSpec) -> None:
        floor = spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[self.length / 2, self.width / 2, 0.1],
            rgba=[0.8, 0.8, 0.78, 1],
            condim=3,
            friction=[0.7, 0.1, 0.1],
        )
        if self.slope:
            floor.quat = self.tilt

    def ground(self, xy: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        if not self.slope:
            return np.zeros(len(xy))
        return xy[:, 0] * self.tan_slope

    def fall_ground(self, xy: np.ndarray) -> np.ndarray:
        """On a slope, the released code's heights of it (`Terrain._create_initial_flat_segm`):
        a staircase of 1 / `DIVISIONS` m treads, each at the plane's height at its lower end, all
        1 / cos(slope) - 1 below the plane (1.5 cm at 10 degrees: the released floor is a tilted
        box 1 m thick, whose top face lies that much above the heights it reads)."""
        if not self.slope:
            return np.zeros(len(xy))
        tread = np.floor(xy[:, 0] * DIVISIONS) / DIVISIONS
        return tread * self.tan_slope - (1 / self.cos_slope - 1)


class Heightfield(Arena):
    """A heightfield laid out like ``config``, one terrain per copy, new for every episode:
    ``draw(rng)`` makes one (default: `generate_terrain`'s corridor, drawn in place). ``grid``:
    the heightmap the task observes (None: none). ``lazy``: a corridor is written only around
    the points whose ground is read, as far as a heightmap reads or a body reaches in a step
    (`TerrainStack.reach`); the environment reads the ground under every head at every step
    (its fall test) and at every placement. For worlds where nothing but the body touches the
    terrain; otherwise all of it is written at each reset. The corridor's flat stretches are a
    plane's, as the released code's were box geoms (`derl.envs.flat_ground`)."""

    def __init__(
        self,
        config: TerrainConfig,
        grid: HeightmapGrid | None = None,
        draw: Callable[[np.random.Generator], Terrain] | None = None,
        lazy: bool = False,
    ) -> None:
        self.config, self.grid, self.draw, self.lazy = config, grid, draw, lazy
        self.half = (config.size_x / 2, config.size_y / 2)

    def build(self, spec: mujoco.MjSpec) -> None:
        add_hfield(spec, self.config, self.grid)
        if self.draw is None:
            add_plane(spec)

    terrains: TerrainStack  # once bound

    def bind(self, env: EnvView) -> None:
        # a heightmap reads this far from the head; a body touches this far within a step
        reach = max(
            0.0 if self.grid is None else self.grid.reach,
            BODY_REACH + MAX_SPEED * env.control_dt,
        )
        self.terrains = TerrainStack(
            self.config, env.model, env.num_envs, self.grid, self.draw, reach if self.lazy else None
        )
        env.set_models(self.terrains.models)
        self.flats = FlatGround(env, self.terrains) if self.draw is None else None

    def reset(self, env: EnvView, ids: np.ndarray) -> None:
        self.terrains.renew(ids, env.rng)

    def posed(self, env: EnvView, ids: np.ndarray) -> None:
        if self.flats is not None:
            self.flats.choose(ids)

    def update(self, env: EnvView) -> None:
        if self.flats is not None:
            self.flats.choose(env.all)

    def ground(self, xy: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        return self.terrains.ground(xy, ids)

    def fall_ground(self, xy: np.ndarray) -> np.ndarray:
        return self.terrains.ground(xy, floored=True)

    def top(self, xy: np.ndarray, half: float, ids: np.ndarray | None = None) -> np.ndarray:
        return self.terrains.top(xy, half, ids)


# --- obstacle: boxes on a corridor --------------------------------------------------------------


class ObstacleConfig(BaseModel):
    """The obstacle corridor, as the released code's (configs/eval/obstacle.yml and
    ``Objects.add_obstacles``); lengths in meters."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    size_x: float = Field(150.0, gt=0)
    size_y: float = Field(60.0, gt=0)
    resolution: float = Field(0.1, gt=0)
    spawn_from_end: float = Field(3.0, gt=0)  # START_FLAT: 3
    end_buffer: float = Field(10.0, ge=0)  # boxes keep clear of both ends: 2 x PLACEMENT_BUFFER_LEN
    count: int = Field(50, ge=0)
    half_sizes: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)  # each footprint half-extent
    height: float = Field(2.0, gt=0)
    tries: int = Field(10, ge=1)  # draws of a box's centre before it is left out

    @field_validator("half_sizes")
    @classmethod
    def _positive(cls, value: tuple[float, ...]) -> tuple[float, ...]:
        if not value or min(value) <= 0:
            raise ValueError(f"half_sizes must be positive, got {value}")
        return value

    @model_validator(mode="after")
    def _room(self) -> ObstacleConfig:
        largest = max(self.half_sizes)
        if self.size_x <= 2 * (self.end_buffer + largest) or self.size_y <= 2 * largest:
            raise ValueError("the corridor leaves no room for the largest box")
        if self.spawn_from_end >= self.end_buffer:
            raise ValueError("the spawn point must lie before the first box")
        return self

    @property
    def start_flat(self) -> float:
        """The box-free length at the back end."""
        return self.end_buffer

    @property
    def terrain(self) -> TerrainConfig:
        """The heightfield's geometry (flat until boxes are drawn into it)."""
        return TerrainConfig.flat(
            size_x=self.size_x,
            size_y=self.size_y,
            resolution=self.resolution,
            max_height=self.height,
            start_flat=self.start_flat,
        )

    def draw(self, rng: np.random.Generator) -> Terrain:
        """One corridor: flat start area, then `draw_obstacles`' boxes."""
        x_min = -self.size_x / 2
        start = x_min + self.start_flat
        segments = (
            Segment("flat", x_min, start, 0.0),
            Segment("boxes", start, -x_min, self.height),
        )
        heights = draw_obstacles(self, rng)
        return Terrain(heights, self.resolution, self.height, segments=segments)


def place_boxes(config: ObstacleConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(m, 2) centres and (m, 2) footprint half-extents of the boxes placed, m <= ``count``:
    each box's half-extents drawn from ``half_sizes``, then up to ``tries`` centres uniformly
    in the corridor (``end_buffer`` from both ends) until its footprint overlaps none placed
    before (the released code's placement grid); a box with no free draw is left out."""
    n, tries = config.count, config.tries
    sizes = np.asarray(config.half_sizes, dtype=np.float64)
    half = sizes[rng.integers(len(sizes), size=(n, 2))]
    low = np.array([-config.size_x / 2 + config.end_buffer, -config.size_y / 2]) + half
    high = np.array([config.size_x / 2 - config.end_buffer, config.size_y / 2]) - half
    draws = rng.uniform(low[:, None], high[:, None], (n, tries, 2))
    centres, halves, m = np.empty((n, 2)), np.empty((n, 2)), 0
    for k in range(n):
        for centre in draws[k]:
            apart = np.abs(centres[:m] - centre) >= halves[:m] + half[k]
            if np.logical_or.reduce(apart, axis=1).all():
                centres[m], halves[m], m = centre, half[k], m + 1
                break
    return centres[:m], halves[:m]


def draw_obstacles(config: ObstacleConfig, rng: np.random.Generator) -> np.ndarray:
    """Heights of the boxes of `place_boxes`, all at once: each box fills the vertices of its
    footprint, clipped to the grid."""
    nrow, ncol = config.terrain.grid_shape
    res = config.resolution
    centre, half = place_boxes(config, rng)
    corner = np.array([-config.size_x / 2, -config.size_y / 2])
    first = np.maximum(np.ceil((centre - half - corner) / res - 1e-9), 0).astype(np.intp)
    last = np.minimum(np.floor((centre + half - corner) / res + 1e-9), [ncol - 1, nrow - 1])
    span = np.arange(int(np.ceil(2 * max(config.half_sizes) / res)) + 2)
    cols, rows = (first[:, k, None] + span for k in (0, 1))  # (m, span) each
    inside = (rows <= last[:, 1, None])[:, :, None] & (cols <= last[:, 0, None])[:, None, :]
    heights = np.zeros((nrow, ncol), dtype=np.float32)
    shape = inside.shape
    rows_at = np.broadcast_to(rows[:, :, None], shape)[inside]
    cols_at = np.broadcast_to(cols[:, None, :], shape)[inside]
    heights[rows_at, cols_at] = config.height
    return heights


# --- escape: a bumpy bowl -----------------------------------------------------------------------


class BowlConfig(BaseModel):
    """The escape bowl (the released code's ``Bowl`` module, derl/envs/modules/bowl.py); lengths
    in meters."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    size: float = Field(100.0, gt=0)
    resolution: float = Field(0.1, gt=0)
    depth: float = Field(1.3, gt=0)  # height scale of the bowl
    bump_spacing: float = Field(2.0, gt=0)  # size / bump_spacing random bump factors a side
    bumps: tuple[float, float] = (0.15, 1.0)
    rim: float = Field(0.84, gt=0, lt=1)  # escape radius / half size: 42 of 50 m

    @field_validator("bumps")
    @classmethod
    def _unit_range(cls, value: tuple[float, float]) -> tuple[float, float]:
        if not 0 <= value[0] <= value[1] <= 1:
            raise ValueError(f"bumps must satisfy 0 <= low <= high <= 1, got {value}")
        return value

    @property
    def terrain(self) -> TerrainConfig:
        """The heightfield's geometry; its scale leaves room for the spline's overshoot."""
        return TerrainConfig.flat(
            size_x=self.size,
            size_y=self.size,
            resolution=self.resolution,
            max_height=BOWL_HEADROOM * self.depth,
        )


BOWL_HEADROOM = 1.3  # max_height / depth: a cubic spline through factors <= 1 stays below 1.3


class Bowl:
    """Escape terrains: ``depth (1 - cos(2 pi r / R)) / 2`` (r from the centre, clipped to
    [0.04 R, R], R the half size: a ring of hills at R/2, low again at the edge) times bump
    factors U[bumps] on a grid of ``size / bump_spacing`` knots a side spanning the bowl,
    resampled to the heightfield by a cubic spline as the released code's ``ndimage.zoom``
    (mirror-prefiltered coefficients, then four B-spline weights a vertex along each axis);
    heights are clipped to [0, max_height]. The profile and the weights are computed at the
    first draw; a draw is a small prefilter and, per run of vertices between two knots, a
    product with 4 coefficients a side: products too small for OpenBLAS to start threads, which
    would fight the simulation's for the cores."""

    def __init__(self, config: BowlConfig) -> None:
        self.config = config
        self.knots = max(4, int(config.size / config.bump_spacing))

    @cached_property
    def _grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The profile; the prefilter (knots, knots); the B-spline weights (n, 4) of each
        vertex's four consecutive knots; the first vertex of each run sharing its first knot,
        and that knot."""
        from scipy import ndimage  # here: 0.2 s of every node's start, for the bowl's alone

        config, k = self.config, self.knots
        n = config.terrain.grid_shape[0]
        unit = np.linspace(-1.0, 1.0, n)
        radius = np.clip(np.hypot(unit[:, None], unit[None, :]), 0.04, 1.0)
        profile = (config.depth * (0.5 - np.cos(2 * np.pi * radius) / 2)).astype(np.float32)
        eye = np.eye(k)
        prefilter = np.stack(
            [ndimage.spline_filter1d(eye[j], order=3, mode="mirror") for j in range(k)], axis=1
        )
        zoomed = np.stack([ndimage.zoom(eye[j], n / k) for j in range(k)], axis=1)  # (n, k)
        taps = zoomed @ np.linalg.inv(prefilter)  # at most 4 consecutive nonzeros a row
        first = np.minimum(np.argmax(np.abs(taps) > 1e-9, axis=1), k - 4)
        weights = np.take_along_axis(taps, first[:, None] + np.arange(4), axis=1)
        runs = np.flatnonzero(np.r_[True, np.diff(first) != 0])
        return profile, prefilter, weights.astype(np.float32), runs, first[runs]

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        profile, prefilter, weights, runs, first = self._grid
        n = len(weights)
        bumps = rng.uniform(*self.config.bumps, (self.knots, self.knots))
        coefficients = (prefilter @ bumps @ prefilter.T).astype(np.float32)
        rows = np.empty((n, self.knots), np.float32)  # along y (rows), at the knots along x
        heights = np.empty((n, n), np.float32)
        ends = np.r_[runs[1:], n]
        for start, end, knot in zip(runs, ends, first, strict=True):
            np.matmul(weights[start:end], coefficients[knot : knot + 4], out=rows[start:end])
        for start, end, knot in zip(runs, ends, first, strict=True):
            np.matmul(rows[:, knot : knot + 4], weights[start:end].T, out=heights[:, start:end])
        heights *= profile
        top = np.float32(self.config.terrain.max_height)
        return np.clip(heights, np.float32(0.0), top, out=heights)

    def terrain(self, rng: np.random.Generator) -> Terrain:
        """One bowl as a terrain laid out like ``config.terrain``."""
        layout = self.config.terrain
        return Terrain(self.draw(rng), layout.resolution, layout.max_height)
