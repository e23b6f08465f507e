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

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from derl.envs.arenas import Bowl, BowlConfig, Floor, Heightfield, ObstacleConfig
from derl.envs.endings import Arrived, Escaped
from derl.envs.heightmap import HeightmapGrid
from derl.envs.objects import CarriedObject, GoalPoint
from derl.envs.observations import GoalSeen, Heightmap, ObjectSeen
from derl.envs.rewards import (
    REWARD_WEIGHTS,
    Ctrl,
    Escape,
    Explore,
    Forward,
    PushObject,
    ReachGoal,
    ReachObject,
    RewardWeights,
)
from derl.envs.task import Arena, Task
from derl.envs.terrain import Range

__all__ = [
    "BallPlacement",
    "BowlConfig",
    "ObstacleConfig",
    "PushBoxPlacement",
    "escape",
    "exploration",
    "incline",
    "manipulate_ball",
    "obstacle",
    "patrol",
    "point_nav",
    "push_box_incline",
]

SPAWN_FROM_END = 2.0  # m (along the slope) between the back edge and the spawn of a slope


# --- goals on the floor: patrol and point navigation -------------------------------------------


def _reach(
    name: str, gym_name: str, size: float, goal: GoalPoint, weights: RewardWeights, end: bool
) -> Task:
    """A goal on a ``size`` x ``size`` floor, spawn at the centre; ``end``: arriving ends it."""
    return Task(
        name=name,
        gym_name=gym_name,
        fitness_component="reach",
        arena=Floor(size, size),
        spawn=(0.0, 0.0),
        props=(goal,),
        rewards=(ReachGoal(goal, weights), Ctrl(weights)),
        observations=(GoalSeen(goal),),
        success=Arrived(goal) if end else None,
    )


def patrol(
    size: float = 60.0, half_length: float = 5.0, weights: RewardWeights | None = None
) -> Task:
    """Run back and forth between x = -half_length and x = +half_length (first goal: +)."""
    w = weights or REWARD_WEIGHTS["patrol"]
    first = np.array([half_length, 0.0])
    goal = GoalPoint(lambda rng, n: first, w.margin, alternate=True)
    return _reach("patrol", "Patrol", size, goal, w, end=False)


def point_nav(size: float = 100.0, weights: RewardWeights | None = None) -> Task:
    """Reach a goal drawn uniformly on the floor (2 m inside its edges); arriving ends the
    episode."""
    w = weights or REWARD_WEIGHTS["point_nav"]
    edge = size / 2 - 2.0
    goal = GoalPoint(lambda rng, n: rng.uniform(-edge, edge, (n, 2)), w.margin)
    return _reach("point_nav", "PointNav", size, goal, w, end=True)


# --- exploration --------------------------------------------------------------------------------


def exploration(
    size: float = 100.0, cell: float = 1.0, weights: RewardWeights | None = None
) -> Task:
    """Visit as many distinct ``cell`` x ``cell`` squares of the floor as possible."""
    w = weights or REWARD_WEIGHTS["exploration"]
    return Task(
        name="exploration",
        gym_name="Exploration",
        fitness_component="explore",
        arena=Floor(size, size),
        spawn=(cell / 2, cell / 2),
        rewards=(Explore(size / 2, cell), Ctrl(w)),
    )


# --- heightfield tasks: obstacle and escape ------------------------------------------------------


def obstacle(
    config: ObstacleConfig | None = None,
    weights: RewardWeights | None = None,
    grid: HeightmapGrid | None = None,
) -> Task:
    """Walk along +x through a field of boxes, seen in the heightmap; FT's reward."""
    config = config or ObstacleConfig()
    w = weights or REWARD_WEIGHTS["obstacle"]
    arena = Heightfield(config.terrain, grid or HeightmapGrid(), config.draw)
    return Task(
        name="obstacle",
        gym_name="Obstacle",
        fitness_component="forward",
        arena=arena,
        spawn=(-config.size_x / 2 + config.start_flat / 2, 0.0),
        rewards=(Forward(w), Ctrl(w)),
        observations=(Heightmap(arena),),
    )


def escape(
    config: BowlConfig | None = None,
    weights: RewardWeights | None = None,
    grid: HeightmapGrid | None = None,
) -> Task:
    """Climb out of a bumpy bowl from its centre; ``escape = r - r_prev + bonus [r >= rim]``,
    and reaching the rim ends the episode."""
    config = config or BowlConfig()
    w = weights or REWARD_WEIGHTS["escape"]
    arena = Heightfield(config.terrain, grid or HeightmapGrid(), Bowl(config).terrain)
    rim = config.rim * config.size / 2
    return Task(
        name="escape",
        gym_name="Escape",
        fitness_component="escape",
        arena=arena,
        spawn=(0.0, 0.0),
        rewards=(Escape(rim, w), Ctrl(w)),
        observations=(Heightmap(arena),),
        success=Escaped(rim),
    )


# --- planes: incline, push box incline, manipulate ball ------------------------------------------


def _slope_spawn(floor: Floor) -> tuple[float, float]:
    """2 m along the slope from the low (back) end, on the centre line."""
    return (-(floor.length / 2 - SPAWN_FROM_END) * floor.cos_slope, 0.0)


def incline(
    length: float = 150.0,
    width: float = 40.0,
    slope: float = 10.0,
    weights: RewardWeights | None = None,
) -> Task:
    """Walk up a 10 degree slope; ``forward`` = x velocity / cos(slope), the speed along it."""
    w = weights or REWARD_WEIGHTS["incline"]
    floor = Floor(length, width, slope)
    return Task(
        name="incline",
        gym_name="Incline",
        fitness_component="forward",
        arena=floor,
        spawn=_slope_spawn(floor),
        rewards=(Forward(w, floor.cos_slope), Ctrl(w)),
    )


def _carry(
    name: str,
    gym_name: str,
    arena: Arena,
    spawn: tuple[float, float],
    obj: CarriedObject,
    weights: RewardWeights,
) -> Task:
    """MVT's reach and push rewards and "object" observation, for ``obj`` on ``arena``."""
    return Task(
        name=name,
        gym_name=gym_name,
        fitness_component="manipulation",
        arena=arena,
        spawn=spawn,
        props=(obj,),
        rewards=(ReachObject(obj, weights), PushObject(obj, weights), Ctrl(weights)),
        observations=(ObjectSeen(obj),),
        metrics={"manipulation": ("reach", "push")},
    )


class PushBoxPlacement(BaseModel):
    """The box of push box incline and where it and its goal go (world x, on the centre line):
    the original's 0.4 m 2 kg box from near the low end to a goal near the high end."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    box_size: float = Field(0.4, gt=0)  # side (the paper says 0.2 m)
    box_mass: float = Field(2.0, gt=0)
    box_ahead: float = Field(3.0, gt=0)  # m from the spawn to the box
    goal_from_end: float = Field(5.0, ge=0)  # m from the far edge to the goal

    def draw(
        self,
        rng: np.random.Generator,
        n: int,
        half: tuple[float, float],
        spawn: tuple[float, float],
    ) -> tuple[np.ndarray, np.ndarray]:
        box = [spawn[0] + self.box_ahead, 0.0]
        goal = [half[0] - self.goal_from_end, 0.0]
        return np.tile(box, (n, 1)), np.tile(goal, (n, 1))


def push_box_incline(
    length: float = 80.0,
    width: float = 40.0,
    slope: float = 10.0,
    placement: PushBoxPlacement | None = None,
    weights: RewardWeights | None = None,
) -> Task:
    """Push a box up a 10 degree slope to a goal near the far end."""
    floor = Floor(length, width, slope)
    spawn = _slope_spawn(floor)
    box = CarriedObject(floor, spawn, placement or PushBoxPlacement())
    w = weights or REWARD_WEIGHTS["push_box_incline"]
    return _carry("push_box_incline", "PushBoxIncline", floor, spawn, box, w)


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
        """The diameter."""
        return 2 * self.radius

    @property
    def box_mass(self) -> float:
        return self.density * 4 / 3 * np.pi * self.radius**3

    def geom(self) -> dict[str, object]:
        """The object's geom made a sphere with the original's contact (condim 6: rolling
        friction; solref -10000 -30)."""
        return {
            "type": mujoco.mjtGeom.mjGEOM_SPHERE,
            "size": [self.radius, 0.0, 0.0],
            "condim": 6,
            "priority": 1,
            "friction": [0.7, 0.005, 0.005],
            "solref": [-10000.0, -30.0],
        }

    def draw(
        self,
        rng: np.random.Generator,
        n: int,
        half: tuple[float, float],
        spawn: tuple[float, float],
    ) -> tuple[np.ndarray, np.ndarray]:
        distance, heading = rng.uniform(*self.near, n), rng.uniform(-np.pi, np.pi, n)
        ball = np.column_stack([np.cos(heading), np.sin(heading)]) * distance[:, None]
        edge = half[0] - self.goal_edge
        return ball + spawn, rng.uniform(-edge, edge, (n, 2))


def manipulate_ball(
    size: float = 30.0,
    placement: BallPlacement | None = None,
    weights: RewardWeights | None = None,
) -> Task:
    """Roll a ball to a goal on a square floor, from its centre. The object keeps MVT's names
    ("box", "box_root")."""
    placement = placement or BallPlacement()
    floor, spawn = Floor(size, size), (0.0, 0.0)
    ball = CarriedObject(floor, spawn, placement, placement.geom())
    w = weights or REWARD_WEIGHTS["manipulate_ball"]
    return _carry("manipulate_ball", "ManipulateBall", floor, spawn, ball, w)
