"""The eight test tasks of the paper (appendix C), on the same batched environment as evolution.

Each follows the released code (agrimgupta92/derl: configs/eval/*.yml, derl/envs/tasks/*.py)
where it is more precise than the paper or disagrees with it; docs/fidelity.md lists each point.
Every task keeps the control cost ``-0.001 |a|^2`` ("ctrl") and the environment's endings (fall,
arena edge, time limit); distances are of the head centre in the ground plane (xy).

- patrol: 60 x 60 m floor; spawn at x = -5, the goal alternates between x = +5 and x = -5
  (y = 0), first +5. "reach" = 100 x the decrease in head-goal distance, +10 on each arrival
  (within 0.5 m), which flips it.
- point_nav: 100 x 100 m floor, spawn at the centre, a goal drawn uniformly each episode (6.5 m
  inside the x edges, 10.5 m inside the y edges); "reach" as in patrol, +10 at every step within
  0.5 m of the goal; arriving does not end the episode.
- obstacle: 150 x 60 m corridor, spawn 3 m from the back edge; 50 boxes (footprint half-sizes
  from {0.5, 1, ..., 3} m, 2 m tall, not overlapping, 10 m clear of both ends) drawn into the
  heightfield each episode; "forward" = x velocity, as FT; the heightmap is observed.
- exploration: 100 x 100 m floor cut into 1 m cells, spawn at the centre; "explore" = +1 for
  each cell the head is in for the first time in the episode (the spawn cell at the first step).
- escape: 100 x 100 m bowl of random bumps, new each episode; "escape" = the per-step increase in
  distance from the centre, the score; "rim" = +100 and success on reaching 42 m (0.84 of the
  half size; the released code's half size less 8 m), paid and not scored, as the released
  code's; the bowl is the released code's cubic-spline bumps.
- incline: 150 x 40 m plane tilted 10 degrees, +x uphill, spawn 2 m (along the slope) from the
  low end; "forward" = x velocity / cos 10 deg, the speed along the slope; a fall is the head
  below 20% of its resting height.
- push_box_incline: 80 x 40 m plane tilted 10 degrees, a 0.4 m 2 kg box at x = -35 and its goal
  at x = +35 (y = 0), spawn as incline; MVT's "reach" and "push" rewards (margin 0.5 m) and
  "object" observation; falls as incline.
- manipulate_ball: 30 x 30 m floor, spawn 2 m from the back edge, a ball (r = 0.2 m, density
  600, rolling friction) placed like MVT's box (15-24 m ahead but no closer than 6.2 m to the
  far edge, within 4.8 m of the centre line) and its goal beyond it (no closer than 6.5 m to the
  far edge: nearly always that); MVT's rewards (margin 0.5 m, the ball reached at its centre)
  and observation.
"""

from __future__ import annotations

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from derl.envs.arenas import Bowl, BowlConfig, Floor, Heightfield, ObstacleConfig
from derl.envs.endings import Escaped
from derl.envs.heightmap import HeightmapGrid
from derl.envs.objects import CarriedObject, FloorCells, ForwardPlacement, GoalPoint
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
    RimBonus,
)
from derl.envs.task import Arena, Task

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
SLOPE_FALL_RATIO = 0.2  # the slopes' STAND_HEIGHT_RATIO in the released code (0.5 elsewhere)


# --- goals on the floor: patrol and point navigation -------------------------------------------


def _reach(
    name: str,
    gym_name: str,
    size: float,
    spawn: tuple[float, float],
    goal: GoalPoint,
    weights: RewardWeights,
) -> Task:
    """A goal on a ``size`` x ``size`` floor; arriving pays, and does not end the episode."""
    return Task(
        name=name,
        gym_name=gym_name,
        fitness_component="reach",
        arena=Floor(size, size),
        spawn=spawn,
        props=(goal,),
        rewards=(ReachGoal(goal, weights), Ctrl(weights)),
        observations=(GoalSeen(goal),),
    )


def patrol(
    size: float = 60.0, half_length: float = 5.0, weights: RewardWeights | None = None
) -> Task:
    """Run back and forth between x = -half_length and x = +half_length, from the first (the
    goal is the other first); the goal's centre is 0.1 m above the floor."""
    w = weights or REWARD_WEIGHTS["patrol"]
    first = np.array([half_length, 0.0])
    goal = GoalPoint(lambda rng, n: first, w.margin, alternate=True, lift=0.1)
    return _reach("patrol", "Patrol", size, (-half_length, 0.0), goal, w)


GOAL_EDGES = (6.5, 10.5)  # m kept free before the x and y edges by point_nav's goals


def point_nav(
    size: float = 100.0,
    weights: RewardWeights | None = None,
    edges: tuple[float, float] = GOAL_EDGES,
) -> Task:
    """From the centre, reach a goal drawn uniformly on the floor, ``edges`` m inside its x and
    y edges (the released code's placement buffers of 3 and 5 m, counted twice, and the goal's
    half size); the bonus is paid at every step within the margin."""
    w = weights or REWARD_WEIGHTS["point_nav"]
    half = np.array([size / 2 - edges[0], size / 2 - edges[1]])
    if (half <= 0).any():
        raise ValueError(f"a {size} m floor leaves no room for goals {edges} m inside its edges")
    goal = GoalPoint(lambda rng, n: rng.uniform(-half, half, (n, 2)), w.margin)
    return _reach("point_nav", "PointNav", size, (0.0, 0.0), goal, w)


# --- exploration --------------------------------------------------------------------------------


def exploration(
    size: float = 100.0, cell: float = 1.0, weights: RewardWeights | None = None
) -> Task:
    """Visit as many distinct ``cell`` x ``cell`` squares of the floor as possible, from its
    centre."""
    w = weights or REWARD_WEIGHTS["exploration"]
    cells = FloorCells(size / 2, cell)
    return Task(
        name="exploration",
        gym_name="Exploration",
        fitness_component="explore",
        arena=Floor(size, size),
        spawn=(0.0, 0.0),
        props=(cells,),
        rewards=(Explore(cells), Ctrl(w)),
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
        spawn=(-config.size_x / 2 + config.spawn_from_end, 0.0),
        rewards=(Forward(w), Ctrl(w)),
        observations=(Heightmap(arena),),
    )


def escape(
    config: BowlConfig | None = None,
    weights: RewardWeights | None = None,
    grid: HeightmapGrid | None = None,
) -> Task:
    """Climb out of a bumpy bowl from its centre; the score ``escape = r - r_prev`` (the
    released ``__reward__forward``), the reward that and ``rim = bonus [r >= rim]``; reaching
    the rim ends the episode."""
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
        rewards=(Escape(), RimBonus(rim, w), Ctrl(w)),
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
        fall_ratio=SLOPE_FALL_RATIO,
    )


def _carry(
    name: str,
    gym_name: str,
    arena: Arena,
    spawn: tuple[float, float],
    obj: CarriedObject,
    weights: RewardWeights,
    fall_ratio: float | None = None,
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
        fall_ratio=fall_ratio,
    )


class PushBoxPlacement(BaseModel):
    """The box of push box incline and where it and its goal go (world x, on the centre line):
    the released code's 0.4 m 2 kg box (``BOX_SIDE: 0.20`` is MuJoCo's half size) at
    ``BOX_POS: [-35, 0]``, its goal at ``GOAL_POS: [35, 0]``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    box_size: float = Field(0.4, gt=0)  # side (the paper says 0.2 m)
    box_mass: float = Field(2.0, gt=0)
    box_x: float = -35.0  # world x of the box
    goal_x: float = 35.0  # world x of the goal

    def draw(
        self,
        rng: np.random.Generator,
        n: int,
        half: tuple[float, float],
        spawn: tuple[float, float],
    ) -> tuple[np.ndarray, np.ndarray]:
        if not -half[0] < self.box_x < self.goal_x < half[0]:
            raise ValueError(f"box at x = {self.box_x} and goal at {self.goal_x} off the slope")
        return np.tile([self.box_x, 0.0], (n, 1)), np.tile([self.goal_x, 0.0], (n, 1))


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
    w = weights or REWARD_WEIGHTS["push_box_incline"]
    box = CarriedObject(floor, spawn, placement or PushBoxPlacement(), w.margin)
    return _carry("push_box_incline", "PushBoxIncline", floor, spawn, box, w, SLOPE_FALL_RATIO)


class BallPlacement(ForwardPlacement):
    """The ball of manipulate ball (the released code's) and where it and its goal go: as MVT's
    box (`ForwardPlacement`; the released task is MVT's on a 30 m flat corridor)."""

    radius: float = Field(0.2, gt=0)
    density: float = Field(600.0, gt=0)  # kg/m^3

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


BALL_SPAWN_FROM_END = 2.0  # m: manipulate ball's START_FLAT in the released code


def manipulate_ball(
    size: float = 30.0,
    placement: BallPlacement | None = None,
    weights: RewardWeights | None = None,
) -> Task:
    """Roll a ball to a goal on a square floor, from 2 m before its back edge. The object keeps
    MVT's names ("box", "box_root"); the agent reaches it at its centre."""
    placement = placement or BallPlacement()
    floor, spawn = Floor(size, size), (-size / 2 + BALL_SPAWN_FROM_END, 0.0)
    w = weights or REWARD_WEIGHTS["manipulate_ball"]
    ball = CarriedObject(floor, spawn, placement, w.margin, placement.geom(), faces=False)
    return _carry("manipulate_ball", "ManipulateBall", floor, spawn, ball, w)
