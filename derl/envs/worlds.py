"""The three evolution worlds of the paper (appendix A and B): FT, VT and MVT, as compositions.

FT and VT reward forward progress, ``w_x v_x - w_c |a|^2`` with w_x = 1, w_c = 0.001; the
fitness is the forward term alone, whose episode sum is 50 x the distance walked along +x.
MVT rewards bringing a box to a goal: ``100 d_ao + 100 d_og - w_c |a|^2`` where d_ao and d_og
are the decreases in agent-box and box-goal distance, plus 10 the first time the agent comes
within 0.75 m of the box and 10 the first time the box comes within 0.75 m of the goal; the
fitness is the reach and push terms without the control cost. Weights: `REWARD_WEIGHTS`.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from derl.envs.arenas import Floor, Heightfield
from derl.envs.heightmap import HeightmapGrid
from derl.envs.objects import CarriedObject
from derl.envs.observations import Heightmap, ObjectSeen
from derl.envs.rewards import REWARD_WEIGHTS, Ctrl, Forward, PushObject, ReachObject, RewardWeights
from derl.envs.task import Task
from derl.envs.terrain import TerrainConfig


def ft(size: float = 150.0, weights: RewardWeights | None = None) -> Task:
    """FT: a ``size`` x ``size`` flat floor; walk along +x from 2 m before its back edge."""
    w = weights or REWARD_WEIGHTS["ft"]
    return Task(
        name="ft",
        gym_name="FT",
        fitness_component="forward",
        arena=Floor(size, size),
        spawn=(-size / 2 + 2.0, 0.0),
        rewards=(Forward(w), Ctrl(w)),
    )


def vt(
    terrain: TerrainConfig | None = None,
    weights: RewardWeights | None = None,
    grid: HeightmapGrid | None = None,
) -> Task:
    """VT: 100 m x 100 m of hills, steps and rubble between flat segments, new every episode;
    walk along +x from the middle of the flat start area, seeing the heightmap."""
    terrain = terrain or TerrainConfig.variable()
    w = weights or REWARD_WEIGHTS["vt"]
    arena = Heightfield(terrain, grid or HeightmapGrid())
    return Task(
        name="vt",
        gym_name="VT",
        fitness_component="forward",
        arena=arena,
        spawn=(-terrain.size_x / 2 + terrain.start_flat / 2, 0.0),
        rewards=(Forward(w), Ctrl(w)),
        observations=(Heightmap(arena),),
    )


class BoxPlacement(BaseModel):
    """MVT's box, and where it and its goal go relative to the spawn point (the original's
    ranges): the box 15-24 m ahead, the goal 15-24 m beyond it, both at a uniform y."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    box_size: float = Field(0.2, gt=0)  # side of the cube (the paper); the original used 0.4
    box_mass: float = Field(1.0, gt=0)
    box_ahead: tuple[float, float] = (15.0, 24.0)
    goal_ahead: tuple[float, float] = (15.0, 24.0)  # beyond the box
    side_buffer: float = Field(5.0, ge=0)  # m kept free along the side edges
    far_buffer: float = Field(6.0, ge=0)  # m kept free before the far edge

    def draw(
        self,
        rng: np.random.Generator,
        n: int,
        half: tuple[float, float],
        spawn: tuple[float, float],
    ) -> tuple[np.ndarray, np.ndarray]:
        x_far = half[0] - self.far_buffer
        y_half = half[1] - self.side_buffer
        box_x = np.minimum(spawn[0] + rng.uniform(*self.box_ahead, n), x_far - 1.0)
        goal_x = np.minimum(box_x + rng.uniform(*self.goal_ahead, n), x_far)
        box = np.stack([box_x, rng.uniform(-y_half, y_half, n)], axis=1)
        goal = np.stack([goal_x, rng.uniform(-y_half, y_half, n)], axis=1)
        return box, goal


def mvt(
    terrain: TerrainConfig | None = None,
    weights: RewardWeights | None = None,
    grid: HeightmapGrid | None = None,
    placement: BoxPlacement | None = None,
) -> Task:
    """MVT: VT's terrain on 60 m x 40 m, a box, and a goal further along +x than the box."""
    terrain = terrain or TerrainConfig.manipulation()
    w = weights or REWARD_WEIGHTS["mvt"]
    arena = Heightfield(terrain, grid or HeightmapGrid())
    spawn = (-terrain.size_x / 2 + terrain.start_flat / 2, 0.0)
    box = CarriedObject(arena, spawn, placement or BoxPlacement())
    return Task(
        name="mvt",
        gym_name="MVT",
        fitness_component="manipulation",
        arena=arena,
        spawn=spawn,
        props=(box,),
        rewards=(ReachObject(box, w), PushObject(box, w), Ctrl(w)),
        observations=(Heightmap(arena), ObjectSeen(box)),
        metrics={"manipulation": ("reach", "push")},
    )
