"""Observations a task adds to the body's proprioception, each a part a task lists."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from derl.envs.arenas import Heightfield
from derl.envs.objects import CarriedObject, GoalPoint
from derl.envs.task import Observation
from derl.envs.view import EnvView


class Heightmap(Observation):
    """ "heightmap": the arena's terrain around the head on a heading-aligned grid (appendix B),
    relative to the ground under the head (`derl.envs.heightmap`)."""

    name: ClassVar[str] = "heightmap"

    def __init__(self, arena: Heightfield) -> None:
        if arena.grid is None:
            raise ValueError("a heightmap observation needs an arena with a heightmap grid")
        self.arena = arena
        self.size = arena.grid.size

    def __call__(self, env: EnvView, ids: np.ndarray) -> np.ndarray:
        terrains = self.arena.terrains
        if ids is env.all:  # the common case: no row selection
            return terrains.heightmap(env.head_pos[:, :2], env.yaw)
        return terrains.heightmap(env.head_pos[ids, :2], env.yaw[ids], ids)


class GoalSeen(Observation):
    """ "goal": the goal relative to the head, in the head frame."""

    name: ClassVar[str] = "goal"
    size = 3

    def __init__(self, goal: GoalPoint) -> None:
        self.goal = goal

    def __call__(self, env: EnvView, ids: np.ndarray) -> np.ndarray:
        goal = env.to_head_frame(self.goal.goal - env.head_pos)
        return goal[ids].astype(np.float32)


class ObjectSeen(Observation):
    """ "object": in the head frame, the object's position and velocity relative to the head's,
    its angular velocity, and its goal's position relative to the head (the released code
    rotates all four into the head frame, derl/envs/modules/objects.py; it takes the angular
    velocity from the free joint's qvel, which MuJoCo gives in the object's own frame, as a
    world vector: derl turns it into the world frame first)."""

    name: ClassVar[str] = "object"
    size = 12

    def __init__(self, obj: CarriedObject) -> None:
        self.obj = obj

    def __call__(self, env: EnvView, ids: np.ndarray) -> np.ndarray:
        obj, head = self.obj, env.head_pos
        parts = np.empty((env.num_envs, 4, 3))  # the four world vectors, then one rotation
        np.subtract(obj.position, head, out=parts[:, 0])
        np.subtract(obj.velocity[:, :3], env.head_vel, out=parts[:, 1])
        parts[:, 2] = obj.angular_velocity()
        np.subtract(obj.goal, head, out=parts[:, 3])
        seen = np.matmul(parts, env.head_rot).reshape(env.num_envs, self.size)  # R^T v, per row
        if ids is not env.all:
            seen = seen[ids]
        return seen.astype(np.float32)
