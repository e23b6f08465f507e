"""A new world for derl: a corridor of stairs, new every episode, and a reward for climbing.

Made of derl's parts (a `Heightfield` arena seen through the `Heightmap` observation, the
`Forward` and `Ctrl` terms) and two of its own: the terrain (`draw_stairs`) and a reward term
(`Climb`). The fitness is `progress`, forward plus climb: a metric summing the two terms, so its
bound comes from theirs (`Climb.step_bound`), with no other edit.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from derl.envs.arenas import Heightfield
from derl.envs.heightmap import HeightmapGrid
from derl.envs.observations import Heightmap
from derl.envs.rewards import Ctrl, Forward, RewardWeights
from derl.envs.task import EpisodeLimits, RewardTerm, Task
from derl.envs.terrain import Terrain, TerrainConfig
from derl.envs.view import MAX_SPEED, EnvView

TERRAIN = TerrainConfig.flat(size_x=40.0, size_y=10.0, max_height=2.0, start_flat=4.0)


def draw_stairs(rng: np.random.Generator, config: TerrainConfig = TERRAIN) -> Terrain:
    """Flat for `start_flat` metres, then treads 0.5-1.0 m deep (drawn), each 5 cm higher, up
    to `max_height`."""
    nrow, ncol = config.grid_shape
    x = np.arange(ncol) * config.resolution - config.size_x / 2
    climbed = x - (x[0] + config.start_flat)
    depth = rng.uniform(0.5, 1.0)
    treads = np.where(climbed > 0, np.floor(climbed / depth) + 1, 0.0)
    heights = np.minimum(0.05 * treads, config.max_height)
    grid = np.broadcast_to(heights, (nrow, ncol))
    return Terrain(grid, config.resolution, config.max_height)


class Climb(RewardTerm):
    """``weight x`` the head's vertical speed (m/s): the height gained, paid as it is gained."""

    name: ClassVar[str] = "climb"

    def __init__(self, weight: float) -> None:
        self.weight = weight

    def __call__(self, env: EnvView) -> np.ndarray:
        return self.weight * (env.head_pos[:, 2] - env.prev_head[:, 2]) / env.control_dt

    def step_bound(self, limits: EpisodeLimits) -> float:
        """derl ends any copy faster than MAX_SPEED, and such a step earns nothing."""
        return abs(self.weight) * MAX_SPEED


def stairs(climb: float = 5.0, weights: RewardWeights | None = None) -> Task:
    """Walk along +x up the stairs; fitness: forward progress plus `climb` x the climbing."""
    w = weights or RewardWeights()
    arena = Heightfield(TERRAIN, HeightmapGrid(), draw_stairs)
    return Task(
        name="stairs",
        gym_name="Stairs",
        fitness_component="progress",
        arena=arena,
        spawn=(-TERRAIN.size_x / 2 + TERRAIN.start_flat / 2, 0.0),
        rewards=(Forward(w), Climb(climb), Ctrl(w)),
        observations=(Heightmap(arena),),
        metrics={"progress": ("forward", "climb")},
    )
