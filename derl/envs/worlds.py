"""The three evolution worlds of the paper (appendix A and B): FT, VT and MVT, as compositions.

FT and VT reward forward progress, ``w_x v_x - w_c |a|^2`` with w_x = 1, w_c = 0.001; the
fitness is the forward term alone, whose episode sum is 50 x the distance walked along +x.
MVT rewards bringing a box to a goal: ``100 d_ao + 100 d_og - w_c |a|^2`` where d_ao and d_og
are the decreases in agent-box and box-goal distance, plus 10 the first time the agent comes
within 0.75 m of the box and 10 at every step the box is within 0.75 m of the goal; the push
term is paid only once the agent has reached the box (the released code); the fitness is the
reach and push terms without the control cost. Weights: `REWARD_WEIGHTS`.
"""

from __future__ import annotations

from pydantic import Field

from derl.envs.arenas import Floor, Heightfield
from derl.envs.heightmap import HeightmapGrid
from derl.envs.objects import CarriedObject, ForwardPlacement
from derl.envs.observations import Heightmap, ObjectSeen
from derl.envs.rewards import REWARD_WEIGHTS, Ctrl, Forward, PushObject, ReachObject, RewardWeights
from derl.envs.task import Task
from derl.envs.terrain import TerrainConfig


def ft(size: float = 150.0, weights: RewardWeights | None = None) -> Task:
    """FT: a ``size`` x ``size`` flat floor; walk along +x from 3 m before its back edge (the
    released code's ``START_FLAT: 3``)."""
    w = weights or REWARD_WEIGHTS["ft"]
    return Task(
        name="ft",
        gym_name="FT",
        fitness_component="forward",
        arena=Floor(size, size),
        spawn=(-size / 2 + 3.0, 0.0),
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
    arena = Heightfield(terrain, grid or HeightmapGrid(), lazy=True)
    return Task(
        name="vt",
        gym_name="VT",
        fitness_component="forward",
        arena=arena,
        spawn=(-terrain.size_x / 2 + terrain.start_flat / 2, 0.0),
        rewards=(Forward(w), Ctrl(w)),
        observations=(Heightmap(arena),),
    )


class BoxPlacement(ForwardPlacement):
    """MVT's box (the released code's: ``BOX_SIDE: 0.20`` is MuJoCo's half size, a 0.4 m cube
    of 1 kg) and where it and its goal go (`ForwardPlacement`: the box 15-24 m ahead, the goal
    15-24 m beyond it)."""

    box_size: float = Field(0.4, gt=0)  # side of the cube
    box_mass: float = Field(1.0, gt=0)


def mvt(
    terrain: TerrainConfig | None = None,
    weights: RewardWeights | None = None,
    placement: BoxPlacement | None = None,
) -> Task:
    """MVT: VT's terrain on 60 m x 40 m, a box, and a goal further along +x than the box. The
    agent sees the box and the goal, not the terrain: the released code's MVT observes no
    heightmap (its configuration lists one, but its manipulation environment never adds it)."""
    terrain = terrain or TerrainConfig.manipulation()
    w = weights or REWARD_WEIGHTS["mvt"]
    arena = Heightfield(terrain)
    spawn = (-terrain.size_x / 2 + terrain.start_flat / 2, 0.0)
    box = CarriedObject(arena, spawn, placement or BoxPlacement(), w.margin)
    return Task(
        name="mvt",
        gym_name="MVT",
        fitness_component="manipulation",
        arena=arena,
        spawn=spawn,
        props=(box,),
        rewards=(ReachObject(box, w), PushObject(box, w), Ctrl(w)),
        observations=(ObjectSeen(box),),
        metrics={"manipulation": ("reach", "push")},
    )
