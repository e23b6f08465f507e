"""The eight test tasks of the paper (appendix C), on the same batched environment as evolution.

Every task keeps the control cost ``-0.001 |a|^2`` ("ctrl") and the environment's endings (fall,
arena edge, time limit); distances are of the head centre in the ground plane (xy).

- patrol: 60 x 60 m floor; the goal alternates between x = +5 and x = -5 (y = 0). "reach" =
  100 x the decrease in head-goal distance, +10 on each arrival (within 0.5 m), which flips it.
- point_nav: 100 x 100 m floor, a goal drawn uniformly each episode; "reach" as in patrol, and the
  episode ends (success) on arrival.
- obstacle: 150 x 60 m corridor with 50 boxes (footprint half-sizes U[0.5, 3] m, 2 m tall) drawn
  into the heightfield each episode; "forward" = x velocity, as FT; the heightmap is observed.
- exploration: 100 x 100 m floor cut into 1 m cells; "explore" = +1 for each cell the head
  enters for the first time in the episode.
- escape: 100 x 100 m bowl of random bumps, new each episode; "escape" = the per-step increase in
  distance from the centre, +100 and success on reaching 84% of the half size (42 m).
- incline: 150 x 40 m plane tilted 10 degrees, +x uphill; "forward" = x velocity / cos 10 deg,
  the speed along the slope.
- push_box_incline: 80 x 40 m plane tilted 10 degrees, a 0.4 m 2 kg box 3 m ahead of the agent,
  the goal 5 m before the far end; MVT's "reach" and "push" rewards and "object" observation.
- manipulate_ball: 30 x 30 m floor, a ball (r = 0.2 m, density 600, rolling friction) 1.5-4 m
  from the agent in any direction, the goal anywhere 3 m inside the edges; MVT's rewards and
  observation.

Where the paper is silent: spawns are the arena centre for patrol, point_nav, escape and the ball
(the centre of the middle cell for exploration, so spawning never pays) and 2 m (along the slope)
from the low end for the corridors and slopes; goals and objects lie on the ground; obstacles
start 10 m after the back edge and may overlap or run past the sides.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import TYPE_CHECKING, ClassVar

import mujoco
import mujoco.batch
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from derl.envs.heightmap import HeightmapGrid
from derl.envs.task import Arrays
from derl.envs.terrain import Range, Segment, Terrain, TerrainConfig
from derl.envs.terrain_stack import TerrainStack
from derl.envs.worlds import Flat, Manipulation, RewardWeights, Variable, ctrl_cost

if TYPE_CHECKING:
    from derl.envs.batched import UnimalEnv

SPAWN_FROM_END = 2.0  # m (along the slope) between the back edge and the spawn of a slope


# --- goals on the floor: patrol and point navigation -------------------------------------------


class _Reach(Flat):
    """A goal on the floor: ``reach = 100 (d_prev - d) + 10 [d <= margin]`` with d the head-goal
    distance; the goal relative to the head, in the head frame, is observed."""

    fitness_component: ClassVar[str] = "reach"

    def __init__(self, size: float, weights: RewardWeights | None) -> None:
        super().__init__(size, weights or RewardWeights(margin=0.5))
        self.spawn = (0.0, 0.0)

    def setup(self, env: UnimalEnv) -> None:
        self.goal = np.zeros((env.num_envs, 3))
        self.dist = np.zeros(env.num_envs)

    def obs_spaces(self) -> dict[str, int]:
        return {"goal": 3}

    def placed(self, env: UnimalEnv, ids: np.ndarray) -> None:
        self.dist[ids] = self._distance(env)[ids]

    def _distance(self, env: UnimalEnv) -> np.ndarray:
        return np.linalg.norm(self.goal[:, :2] - env.head_pos[:, :2], axis=1)

    def arrived(self) -> np.ndarray:
        return self.dist <= self.weights.margin

    def rewards(self, env: UnimalEnv) -> Arrays:
        w, dist = self.weights, self._distance(env)
        reach = w.reach * (self.dist - dist) + w.bonus * (dist <= w.margin)
        self.dist = dist
        return {"reach": reach, "ctrl": ctrl_cost(env, w)}

    def observe(self, env: UnimalEnv, ids: np.ndarray) -> Arrays:
        goal = env.to_head_frame(self.goal - env.head_pos)
        return {"goal": goal[ids].astype(np.float32)}


class Patrol(_Reach):
    """Run back and forth between x = -half_length and x = +half_length (first goal: +)."""

    name: ClassVar[str] = "patrol"
    gym_name: ClassVar[str] = "Patrol"

    def __init__(
        self, size: float = 60.0, half_length: float = 5.0, weights: RewardWeights | None = None
    ) -> None:
        super().__init__(size, weights)
        self.half_length = half_length

    def reset(self, env: UnimalEnv, ids: np.ndarray) -> None:
        self.goal[ids] = [self.half_length, 0.0, 0.0]

    def rewards(self, env: UnimalEnv) -> Arrays:
        terms = super().rewards(env)
        arrived = self.arrived()
        self.goal[arrived, 0] *= -1.0
        self.dist[arrived] = self._distance(env)[arrived]
        return terms


class PointNav(_Reach):
    """Reach a goal drawn uniformly in the arena (kept 2 m inside its edges); arriving ends the
    episode, so its return is 100 x the start distance + 10 less the control cost."""

    name: ClassVar[str] = "point_nav"
    gym_name: ClassVar[str] = "PointNav"

    def __init__(self, size: float = 100.0, weights: RewardWeights | None = None) -> None:
        super().__init__(size, weights)

    def reset(self, env: UnimalEnv, ids: np.ndarray) -> None:
        edge = self.arena[0] - 2.0
        self.goal[ids, :2] = env.rng.uniform(-edge, edge, (len(ids), 2))

    def success(self, env: UnimalEnv) -> np.ndarray:
        return self.arrived()


# --- exploration --------------------------------------------------------------------------------


class Exploration(Flat):
    """Visit as many distinct ``cell`` x ``cell`` squares of the floor as possible."""

    name: ClassVar[str] = "exploration"
    gym_name: ClassVar[str] = "Exploration"
    fitness_component: ClassVar[str] = "explore"

    def __init__(
        self, size: float = 100.0, cell: float = 1.0, weights: RewardWeights | None = None
    ) -> None:
        super().__init__(size, weights)
        self.cell = cell
        self.cells = round(size / cell)
        self.spawn = (cell / 2, cell / 2)

    def setup(self, env: UnimalEnv) -> None:
        self.visited = np.zeros((env.num_envs, self.cells, self.cells), dtype=bool)

    def _cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(column, row) of the cell under each point; points off the floor count as its edge."""
        index = np.floor((xy + self.arena[0]) / self.cell).astype(np.intp)
        index = np.clip(index, 0, self.cells - 1)
        return index[:, 0], index[:, 1]

    def placed(self, env: UnimalEnv, ids: np.ndarray) -> None:
        self.visited[ids] = False
        col, row = self._cell(env.head_pos[ids, :2])
        self.visited[ids, row, col] = True

    def rewards(self, env: UnimalEnv) -> Arrays:
        col, row = self._cell(env.head_pos[:, :2])
        copies = np.arange(env.num_envs)
        new = ~self.visited[copies, row, col]
        self.visited[copies, row, col] = True
        return {"explore": new.astype(np.float64), "ctrl": ctrl_cost(env, self.weights)}


# --- heightfield tasks: obstacle and escape ------------------------------------------------------


class ObstacleConfig(BaseModel):
    """The obstacle corridor; lengths in meters. The paper's sizes and the original's boxes."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    size_x: float = Field(150.0, gt=0)
    size_y: float = Field(60.0, gt=0)
    resolution: float = Field(0.1, gt=0)
    start_flat: float = Field(10.0, ge=0)  # free of boxes at the back end; spawn in its middle
    count: int = Field(50, ge=0)
    half_size: Range = (0.5, 3.0)  # footprint half-extents, each U[half_size]
    height: float = Field(2.0, gt=0)

    @field_validator("half_size")
    @classmethod
    def _positive(cls, value: Range) -> Range:
        if not 0 < value[0] <= value[1]:
            raise ValueError(f"half_size must satisfy 0 < low <= high, got {value}")
        return value

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


def draw_obstacles(config: ObstacleConfig, rng: np.random.Generator) -> np.ndarray:
    """Heights of ``count`` boxes centred uniformly beyond the start area, all boxes at once:
    each box fills the vertices of its footprint, clipped to the grid."""
    nrow, ncol = config.terrain.grid_shape
    res, n = config.resolution, config.count
    half = rng.uniform(*config.half_size, (n, 2))
    low = np.array([-config.size_x / 2 + config.start_flat, -config.size_y / 2])
    high = np.array([config.size_x / 2, config.size_y / 2])
    centre = rng.uniform(low + half * [1, 0], high, (n, 2))
    corner = np.array([-config.size_x / 2, -config.size_y / 2])
    first = np.maximum(np.ceil((centre - half - corner) / res - 1e-9), 0).astype(np.intp)
    last = np.minimum(np.floor((centre + half - corner) / res + 1e-9), [ncol - 1, nrow - 1])
    span = np.arange(int(np.ceil(2 * config.half_size[1] / res)) + 2)
    cols, rows = (first[:, k, None] + span for k in (0, 1))  # (n, span) each
    inside = (rows <= last[:, 1, None])[:, :, None] & (cols <= last[:, 0, None])[:, None, :]
    heights = np.zeros((nrow, ncol), dtype=np.float32)
    shape = inside.shape
    rows_at = np.broadcast_to(rows[:, :, None], shape)[inside]
    cols_at = np.broadcast_to(cols[:, None, :], shape)[inside]
    heights[rows_at, cols_at] = config.height
    return heights


class Obstacle(Variable):
    """Walk along +x through a field of boxes, seen in the heightmap; FT's reward."""

    name: ClassVar[str] = "obstacle"
    gym_name: ClassVar[str] = "Obstacle"

    def __init__(
        self,
        config: ObstacleConfig | None = None,
        weights: RewardWeights | None = None,
        grid: HeightmapGrid | None = None,
    ) -> None:
        self.config = config or ObstacleConfig()
        super().__init__(self.config.terrain, weights, grid)

    def setup(self, env: UnimalEnv) -> None:
        self.terrains = TerrainStack(self.terrain, env.batch, self.grid, self._draw)

    def _draw(self, rng: np.random.Generator) -> Terrain:
        config, x_min = self.config, -self.config.size_x / 2
        start = x_min + config.start_flat
        segments = (
            Segment("flat", x_min, start, 0.0),
            Segment("boxes", start, -x_min, config.height),
        )
        heights = draw_obstacles(config, rng)
        return Terrain(heights, config.resolution, self.terrain.max_height, segments=segments)


class BowlConfig(BaseModel):
    """The escape bowl (the original's ``Bowl`` module); lengths in meters."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    size: float = Field(100.0, gt=0)
    resolution: float = Field(0.1, gt=0)
    depth: float = Field(1.3, gt=0)  # height scale of the bowl
    bump_spacing: float = Field(2.0, gt=0)  # random bump factors on this grid, interpolated
    bumps: tuple[float, float] = (0.15, 1.0)
    rim: float = Field(0.84, gt=0, lt=1)  # escape radius / half size: 42 of 50 m
    bonus: float = 100.0

    @field_validator("bumps")
    @classmethod
    def _unit_range(cls, value: tuple[float, float]) -> tuple[float, float]:
        if not 0 <= value[0] <= value[1] <= 1:
            raise ValueError(f"bumps must satisfy 0 <= low <= high <= 1, got {value}")
        return value

    @property
    def terrain(self) -> TerrainConfig:
        return TerrainConfig.flat(
            size_x=self.size, size_y=self.size, resolution=self.resolution, max_height=self.depth
        )


class Bowl:
    """Escape terrains: ``depth (1 - cos(2 pi r / R)) / 2`` (r from the centre, clipped to
    [0.04 R, R], R the half size: a ring of hills at R/2, low again at the edge) times bump
    factors U[bumps] on a ``bump_spacing`` grid, interpolated bilinearly. The profile and the
    interpolation indices are computed once; a draw is two gathers (no BLAS: its threads fight
    the simulation's for the cores)."""

    def __init__(self, config: BowlConfig) -> None:
        self.config = config
        n = config.terrain.grid_shape[0]
        unit = np.linspace(-1.0, 1.0, n)
        radius = np.clip(np.hypot(unit[:, None], unit[None, :]), 0.04, 1.0)
        profile = config.depth * (0.5 - np.cos(2 * np.pi * radius) / 2)
        self.profile = profile.astype(np.float32)
        self.knots = max(2, round(config.size / config.bump_spacing) + 1)
        position = np.linspace(0.0, self.knots - 1, n)
        self.left = np.minimum(position.astype(np.intp), self.knots - 2)  # knot before vertex
        self.right = (position - self.left).astype(np.float32)  # weight of the knot after it

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        bumps = rng.uniform(*self.config.bumps, (self.knots, self.knots)).astype(np.float32)
        left, right = self.left, self.right
        rows = bumps[left] + (bumps[left + 1] - bumps[left]) * right[:, None]  # (n, knots)
        low, heights = rows[:, left], rows[:, left + 1]  # (n, n) each
        heights -= low
        heights *= right
        heights += low
        heights *= self.profile
        return np.minimum(heights, np.float32(self.config.depth), out=heights)  # float32 rounding


class Escape(Variable):
    """Climb out of a bumpy bowl from its centre; ``escape = r - r_prev + bonus [r >= rim]``."""

    name: ClassVar[str] = "escape"
    gym_name: ClassVar[str] = "Escape"
    fitness_component: ClassVar[str] = "escape"

    def __init__(
        self,
        config: BowlConfig | None = None,
        weights: RewardWeights | None = None,
        grid: HeightmapGrid | None = None,
    ) -> None:
        self.config = config or BowlConfig()
        super().__init__(self.config.terrain, weights, grid)
        self.spawn = (0.0, 0.0)
        self.rim = self.config.rim * self.config.size / 2

    def setup(self, env: UnimalEnv) -> None:
        bowl, layout = Bowl(self.config), self.terrain
        self.terrains = TerrainStack(
            layout,
            env.batch,
            self.grid,
            lambda rng: Terrain(bowl.draw(rng), layout.resolution, layout.max_height),
        )

    def rewards(self, env: UnimalEnv) -> Arrays:
        radius = np.linalg.norm(env.head_pos[:, :2], axis=1)
        gain = radius - np.linalg.norm(env.prev_head[:, :2], axis=1)
        escape = gain + self.config.bonus * (radius >= self.rim)
        return {"escape": escape, "ctrl": ctrl_cost(env, self.weights)}

    def success(self, env: UnimalEnv) -> np.ndarray:
        return np.linalg.norm(env.head_pos[:, :2], axis=1) >= self.rim


# --- planes: incline, push box incline, manipulate ball ------------------------------------------


class _Plane(Variable):
    """FT's floor, ``length`` (along the slope) x ``width``, tilted ``slope`` degrees about y so
    that +x goes uphill, standing in for `Variable`'s heightfield: nothing to renew, no heightmap.

    It derives from `Variable` only to sit between `Manipulation` and `Variable` in the method
    resolution order (``class T(Manipulation, _Plane)``): `Manipulation` puts its object, goal,
    rewards and observation on top of the world its ``super()`` calls reach.
    """

    def __init__(
        self, length: float, width: float, slope: float, weights: RewardWeights | None
    ) -> None:
        self.weights = weights or RewardWeights()
        self.length = length
        self.angle = np.deg2rad(slope)
        self.tilt = [np.cos(self.angle / 2), 0.0, -np.sin(self.angle / 2), 0.0]  # quaternion
        along = np.cos(self.angle)
        self.arena = (length / 2 * along, width / 2)
        self.spawn = (-(length / 2 - SPAWN_FROM_END) * along, 0.0)

    def build(self, spec: mujoco.MjSpec) -> None:
        Flat.build(self, spec)
        floor = spec.geom("floor")
        floor.size[0] = self.length / 2
        floor.quat = self.tilt

    def setup(self, env: UnimalEnv) -> None:
        """Nothing to bind: the plane is part of the compiled model."""

    def obs_spaces(self) -> dict[str, int]:
        return {}

    def start(self, env: UnimalEnv) -> None:
        """Nothing carried between episodes."""

    def reset(self, env: UnimalEnv, ids: np.ndarray) -> None:
        """Nothing to renew."""

    def ground(self, env: UnimalEnv, xy: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        return xy[:, 0] * np.tan(self.angle)

    def observe(self, env: UnimalEnv, ids: np.ndarray) -> Arrays:
        return {}


class Incline(_Plane):
    """Walk up a 10 degree slope; ``forward`` = x velocity / cos(slope), the speed along it."""

    name: ClassVar[str] = "incline"
    gym_name: ClassVar[str] = "Incline"

    def __init__(
        self,
        length: float = 150.0,
        width: float = 40.0,
        slope: float = 10.0,
        weights: RewardWeights | None = None,
    ) -> None:
        super().__init__(length, width, slope, weights)

    def rewards(self, env: UnimalEnv) -> Arrays:
        terms = super().rewards(env)
        terms["forward"] /= np.cos(self.angle)
        return terms


class _Carry(Manipulation, _Plane):
    """MVT's object, goal marker, reach and push rewards and "object" observation, inherited
    whole, on a plane; the object rests flat on it where `_place` says, the goal under it.

    (`Manipulation.reset` is not reused: it reads the ground from VT's ``terrains``, which a
    plane must not have, since `derl.envs.video` takes any ``terrains`` for a `TerrainStack`.)
    """

    @abstractmethod
    def _place(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) object and (n, 2) goal positions for n new episodes."""

    def reset(self, env: UnimalEnv, ids: np.ndarray) -> None:
        obj, goal = self._place(env.rng, len(ids))
        q, half = self.box_qpos, self.placement.box_size / 2
        env.qpos[ids, q : q + 2] = obj
        env.qpos[ids, q + 2] = self.ground(env, obj) + half / np.cos(self.angle) + 0.01
        env.qpos[ids, q + 3 : q + 7] = self.tilt
        self.goal[ids] = np.column_stack([goal, self.ground(env, goal)])
        self.mocap_pos[ids, 0] = self.goal[ids]


class PushBoxPlacement(BaseModel):
    """The box of push box incline and where it and its goal go (world x, on the centre line):
    the original's 0.4 m 2 kg box from near the low end to a goal near the high end."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    box_size: float = Field(0.4, gt=0)  # side (the paper says 0.2 m)
    box_mass: float = Field(2.0, gt=0)
    box_ahead: float = Field(3.0, gt=0)  # m from the spawn to the box
    goal_from_end: float = Field(5.0, ge=0)  # m from the far edge to the goal


class PushBoxIncline(_Carry):
    """Push a box up a 10 degree slope to a goal near the far end."""

    name: ClassVar[str] = "push_box_incline"
    gym_name: ClassVar[str] = "PushBoxIncline"

    def __init__(
        self,
        length: float = 80.0,
        width: float = 40.0,
        slope: float = 10.0,
        placement: PushBoxPlacement | None = None,
        weights: RewardWeights | None = None,
    ) -> None:
        _Plane.__init__(self, length, width, slope, weights)
        self.placement = placement or PushBoxPlacement()

    def _place(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        box = [self.spawn[0] + self.placement.box_ahead, 0.0]
        goal = [self.arena[0] - self.placement.goal_from_end, 0.0]
        return np.tile(box, (n, 1)), np.tile(goal, (n, 1))


class BallPlacement(BaseModel):
    """The ball of manipulate ball (the original's) and where it and its goal go."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    radius: float = Field(0.2, gt=0)
    density: float = Field(600.0, gt=0)  # kg/m^3
    near: Range = (1.5, 4.0)  # m from the spawn, in any direction
    goal_edge: float = Field(3.0, ge=0)  # goal uniform in the arena, this far inside its edges

    @field_validator("near")
    @classmethod
    def _ordered(cls, value: Range) -> Range:
        if not 0 <= value[0] <= value[1]:
            raise ValueError(f"near must satisfy 0 <= low <= high, got {value}")
        return value

    @property
    def box_size(self) -> float:
        """The diameter, as `Manipulation` sizes its object."""
        return 2 * self.radius

    @property
    def box_mass(self) -> float:
        return self.density * 4 / 3 * np.pi * self.radius**3


class ManipulateBall(_Carry):
    """Roll a ball to a goal on a square floor, from its centre.

    The object is MVT's body made a sphere with the original's contact (condim 6: rolling
    friction; solref -10000 -30); it keeps MVT's names ("box", "box_root").
    """

    name: ClassVar[str] = "manipulate_ball"
    gym_name: ClassVar[str] = "ManipulateBall"

    def __init__(
        self,
        size: float = 30.0,
        placement: BallPlacement | None = None,
        weights: RewardWeights | None = None,
    ) -> None:
        _Plane.__init__(self, size, size, 0.0, weights)
        self.spawn = (0.0, 0.0)
        self.placement = placement or BallPlacement()

    def build(self, spec: mujoco.MjSpec) -> None:
        super().build(spec)
        ball = spec.geom("box")
        ball.type = mujoco.mjtGeom.mjGEOM_SPHERE
        ball.size = [self.placement.radius, 0.0, 0.0]
        ball.condim = 6
        ball.priority = 1
        ball.friction = [0.7, 0.005, 0.005]
        ball.solref = [-10000.0, -30.0]

    def _place(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        p = self.placement
        distance, heading = rng.uniform(*p.near, n), rng.uniform(-np.pi, np.pi, n)
        ball = np.column_stack([np.cos(heading), np.sin(heading)]) * distance[:, None]
        edge = self.arena[0] - p.goal_edge
        return ball + self.spawn, rng.uniform(-edge, edge, (n, 2))
