"""The three evolution worlds of the paper (appendix A and B): FT, VT and MVT.

FT and VT reward forward progress, ``w_x v_x - w_c |a|^2`` with w_x = 1, w_c = 0.001; the
fitness is the forward term alone, whose episode sum is 50 x the distance walked along +x.
MVT rewards bringing a box to a goal: ``100 d_ao + 100 d_og - w_c |a|^2`` where d_ao and d_og
are the decreases in agent-box and box-goal distance, plus 10 the first time the agent comes
within 0.75 m of the box and 10 the first time the box comes within 0.75 m of the goal; the
fitness is the reach and push terms without the control cost.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from derl.envs.heightmap import HeightmapGrid
from derl.envs.task import Arrays, Task
from derl.envs.terrain import TerrainConfig
from derl.envs.terrain_stack import TerrainStack, add_hfield

if TYPE_CHECKING:
    from derl.envs.batched import UnimalEnv

CONTROL_DT = 0.02  # s per control step: 4 x 5 ms
BODY_REACH = 2.0  # m: no limb tip is further than this from the head


class RewardWeights(BaseModel):
    """Weights of the paper's reward terms."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    forward: float = 1.0
    ctrl: float = Field(1e-3, ge=0)
    reach: float = 100.0
    push: float = 100.0
    bonus: float = 10.0
    margin: float = Field(0.75, gt=0)


def ctrl_cost(env: UnimalEnv, weights: RewardWeights) -> np.ndarray:
    return -weights.ctrl * np.add.reduce(np.square(env.ctrl), axis=1)


class Flat(Task):
    """FT: a 150 m x 150 m flat arena; walk along +x from one end."""

    name: ClassVar[str] = "ft"
    gym_name: ClassVar[str] = "FT"
    fitness_component: ClassVar[str] = "forward"

    def __init__(self, size: float = 150.0, weights: RewardWeights | None = None) -> None:
        self.weights = weights or RewardWeights()
        self.arena = (size / 2, size / 2)
        self.spawn = (-size / 2 + 2.0, 0.0)

    def build(self, spec: mujoco.MjSpec) -> None:
        spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[self.arena[0], self.arena[1], 0.1],
            rgba=[0.8, 0.8, 0.78, 1],
            condim=3,
            friction=[0.7, 0.1, 0.1],
        )

    def rewards(self, env: UnimalEnv) -> Arrays:
        velocity = (env.head_pos[:, 0] - env.prev_head[:, 0]) / CONTROL_DT
        return {"forward": self.weights.forward * velocity, "ctrl": ctrl_cost(env, self.weights)}


class Variable(Flat):
    """VT: 100 m x 100 m of hills, steps and rubble between flat segments, new every episode;
    the body also sees the heightmap."""

    name: ClassVar[str] = "vt"
    gym_name: ClassVar[str] = "VT"

    def __init__(
        self,
        terrain: TerrainConfig | None = None,
        weights: RewardWeights | None = None,
        grid: HeightmapGrid | None = None,
    ) -> None:
        self.terrain = terrain or TerrainConfig.variable()
        self.weights = weights or RewardWeights()
        self.grid = grid or HeightmapGrid()
        self.arena = (self.terrain.size_x / 2, self.terrain.size_y / 2)
        self.spawn = (-self.terrain.size_x / 2 + self.terrain.start_flat / 2, 0.0)

    def build(self, spec: mujoco.MjSpec) -> None:
        add_hfield(spec, self.terrain)

    def setup(self, env: UnimalEnv) -> None:
        self.terrains = TerrainStack(self.terrain, env.batch, self.grid)

    def obs_spaces(self) -> dict[str, int]:
        return {"heightmap": self.grid.size}

    def start(self, env: UnimalEnv) -> None:
        self.terrains.forget()

    def reset(self, env: UnimalEnv, ids: np.ndarray) -> None:
        self.terrains.renew(ids, env.rng, self.grid.reach + BODY_REACH)

    def ground(self, env: UnimalEnv, xy: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        return self.terrains.ground(xy, ids)

    def observe(self, env: UnimalEnv, ids: np.ndarray) -> Arrays:
        self.terrains.track(env.head_pos[:, 0])
        if ids is env.all:  # the common case: no row selection
            return {"heightmap": self.terrains.heightmap(env.head_pos[:, :2], env.yaw)}
        xy, yaw = env.head_pos[ids, :2], env.yaw[ids]
        return {"heightmap": self.terrains.heightmap(xy, yaw, ids)}


class BoxPlacement(BaseModel):
    """Where MVT's box and goal go, relative to the spawn point (the original's ranges)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    box_size: float = Field(0.2, gt=0)  # side of the cube (the paper); the original used 0.4
    box_mass: float = Field(1.0, gt=0)
    box_ahead: tuple[float, float] = (15.0, 24.0)
    goal_ahead: tuple[float, float] = (15.0, 24.0)  # beyond the box
    side_buffer: float = Field(5.0, ge=0)  # m kept free along the side edges
    far_buffer: float = Field(6.0, ge=0)  # m kept free before the far edge


class Manipulation(Variable):
    """MVT: VT terrain on 60 m x 40 m, a box, and a goal further along +x than the box."""

    name: ClassVar[str] = "mvt"
    gym_name: ClassVar[str] = "MVT"
    fitness_component: ClassVar[str] = "manipulation"

    def __init__(
        self,
        terrain: TerrainConfig | None = None,
        weights: RewardWeights | None = None,
        grid: HeightmapGrid | None = None,
        placement: BoxPlacement | None = None,
    ) -> None:
        super().__init__(terrain or TerrainConfig.manipulation(), weights, grid)
        self.placement = placement or BoxPlacement()

    def build(self, spec: mujoco.MjSpec) -> None:
        super().build(spec)
        half = self.placement.box_size / 2
        box = spec.worldbody.add_body(name="box", pos=[0, 0, half])
        box.add_freejoint(name="box_root")
        box.add_geom(
            name="box",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[half] * 3,
            mass=self.placement.box_mass,
            rgba=[0.85, 0.7, 0.2, 1],
            condim=3,
        )
        goal = spec.worldbody.add_body(name="goal", mocap=True, pos=[0, 0, 0])
        goal.add_geom(
            name="goal",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.25, 0.25, 0.01],
            rgba=[0.85, 0.15, 0.15, 0.6],
            contype=0,
            conaffinity=0,
        )

    def setup(self, env: UnimalEnv) -> None:
        super().setup(env)
        joint = env.model.joint("box_root")
        self.box_qpos = int(joint.qposadr[0])
        self.box_dof = int(joint.dofadr[0])
        self.mocap_pos = env.batch.bind("mocap_pos")
        self.goal = np.zeros((env.num_envs, 3))
        self.reach_dist = np.zeros(env.num_envs)
        self.goal_dist = np.zeros(env.num_envs)
        self.reached = np.zeros(env.num_envs, dtype=bool)
        self.delivered = np.zeros(env.num_envs, dtype=bool)

    def obs_spaces(self) -> dict[str, int]:
        return {**super().obs_spaces(), "object": 12}

    def box_pos(self, env: UnimalEnv) -> np.ndarray:
        return env.qpos[:, self.box_qpos : self.box_qpos + 3]

    def reset(self, env: UnimalEnv, ids: np.ndarray) -> None:
        super().reset(env, ids)
        p, rng, n = self.placement, env.rng, len(ids)
        x_far = self.arena[0] - p.far_buffer
        y_half = self.arena[1] - p.side_buffer
        box_x = np.minimum(self.spawn[0] + rng.uniform(*p.box_ahead, n), x_far - 1.0)
        goal_x = np.minimum(box_x + rng.uniform(*p.goal_ahead, n), x_far)
        box_xy = np.stack([box_x, rng.uniform(-y_half, y_half, n)], axis=1)
        goal_xy = np.stack([goal_x, rng.uniform(-y_half, y_half, n)], axis=1)
        box_z = self.terrains.ground(box_xy, ids) + p.box_size / 2 + 0.01
        qpos = env.qpos[ids]
        qpos[:, self.box_qpos : self.box_qpos + 3] = np.column_stack([box_xy, box_z])
        qpos[:, self.box_qpos + 3 : self.box_qpos + 7] = [1.0, 0.0, 0.0, 0.0]
        env.qpos[ids] = qpos
        self.goal[ids] = np.column_stack([goal_xy, self.terrains.ground(goal_xy, ids)])
        self.mocap_pos[ids, 0] = self.goal[ids]

    def placed(self, env: UnimalEnv, ids: np.ndarray) -> None:
        self.reach_dist[ids] = self._reach_distance(env)[ids]
        self.goal_dist[ids] = self._goal_distance(env)[ids]
        self.reached[ids] = False
        self.delivered[ids] = False

    def _reach_distance(self, env: UnimalEnv) -> np.ndarray:
        points = env.agent_points()
        return np.linalg.norm(points - self.box_pos(env)[:, None], axis=2).min(axis=1)

    def _goal_distance(self, env: UnimalEnv) -> np.ndarray:
        return np.linalg.norm(self.box_pos(env)[:, :2] - self.goal[:, :2], axis=1)

    def rewards(self, env: UnimalEnv) -> Arrays:
        w = self.weights
        reach, goal = self._reach_distance(env), self._goal_distance(env)
        reached_now = ~self.reached & (reach < w.margin)
        delivered_now = ~self.delivered & (goal < w.margin)
        terms = {
            "reach": w.reach * (self.reach_dist - reach) + w.bonus * reached_now,
            "push": w.push * (self.goal_dist - goal) + w.bonus * delivered_now,
            "ctrl": ctrl_cost(env, w),
        }
        self.reach_dist, self.goal_dist = reach, goal
        self.reached |= reached_now
        self.delivered |= delivered_now
        return terms

    def metrics(self, env: UnimalEnv, terms: Arrays) -> Arrays:
        return {"manipulation": terms["reach"] + terms["push"]}

    def observe(self, env: UnimalEnv, ids: np.ndarray) -> Arrays:
        box = self.box_pos(env)
        box_vel = env.qvel[:, self.box_dof : self.box_dof + 3] - env.head_vel
        box_angvel = env.qvel[:, self.box_dof + 3 : self.box_dof + 6]
        obj = np.concatenate(
            [
                env.to_head_frame(box - env.head_pos),
                env.to_head_frame(box_vel),
                box_angvel,
                env.to_head_frame(self.goal - env.head_pos),
            ],
            axis=1,
            dtype=np.float32,
        )
        return {**super().observe(env, ids), "object": obj[ids]}
