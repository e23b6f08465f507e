"""Props: what a task puts in its arena each episode. `GoalPoint` is a goal for the head;
`CarriedObject` is a free body (a box, or a ball) and the goal marker it is to be brought to.
Reward terms, observations and success tests read their state."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Protocol

import mujoco
import numpy as np

from derl.envs.task import Arena, Part
from derl.envs.view import EnvView

Draw = Callable[[np.random.Generator, int], np.ndarray]


class GoalPoint(Part):
    """A goal on the ground: ``draw(rng, n)`` gives (n, 2) positions for n new episodes. After
    each step, ``gain`` is the decrease in head-goal distance (xy) and ``arrived`` whether the
    head is within ``margin``; with ``alternate``, an arrival mirrors the goal's x (patrol)."""

    def __init__(self, draw: Draw, margin: float, alternate: bool = False) -> None:
        self.draw, self.margin, self.alternate = draw, margin, alternate

    def bind(self, env: EnvView) -> None:
        n = env.num_envs
        self.goal = np.zeros((n, 3))
        self.dist = np.zeros(n)
        self.gain = np.zeros(n)
        self.arrived = np.zeros(n, dtype=bool)

    def distance(self, env: EnvView) -> np.ndarray:
        return np.linalg.norm(self.goal[:, :2] - env.head_pos[:, :2], axis=1)

    def reset(self, env: EnvView, ids: np.ndarray) -> None:
        self.goal[ids, :2] = self.draw(env.rng, len(ids))

    def placed(self, env: EnvView, ids: np.ndarray) -> None:
        self.dist[ids] = self.distance(env)[ids]

    def update(self, env: EnvView) -> None:
        dist = self.distance(env)
        self.gain = self.dist - dist
        self.arrived = dist <= self.margin
        self.dist = dist
        if self.alternate:
            self.goal[self.arrived, 0] *= -1.0
            self.dist[self.arrived] = self.distance(env)[self.arrived]


class ObjectPlacement(Protocol):
    """An object's size and mass, and where it and its goal go each episode."""

    @property
    def box_size(self) -> float:
        """Height of the object (the cube's side, the ball's diameter), m."""
        ...

    @property
    def box_mass(self) -> float: ...

    def draw(
        self,
        rng: np.random.Generator,
        n: int,
        half: tuple[float, float],
        spawn: tuple[float, float],
    ) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) object and (n, 2) goal positions in an arena of half extents ``half``."""
        ...


class CarriedObject(Part):
    """A cube (body "box", free joint "box_root", geom "box"; ``geom`` overrides attributes of
    the geom, e.g. to make it a ball) resting on ``arena`` where ``placement`` says, and a goal
    marker (mocap body "goal") on the ground. `position` is the object's live (N, 3) centre,
    `velocity` its (N, 6) linear and angular velocity, `goal` (N, 3) its goals."""

    def __init__(
        self,
        arena: Arena,
        spawn: tuple[float, float],
        placement: ObjectPlacement,
        geom: Mapping[str, object] | None = None,
    ) -> None:
        self.arena, self.spawn, self.placement = arena, spawn, placement
        self.geom = dict(geom or {})
        self.half = placement.box_size / 2

    def build(self, spec: mujoco.MjSpec) -> None:
        body = spec.worldbody.add_body(name="box", pos=[0, 0, self.half])
        body.add_freejoint(name="box_root")
        geom = body.add_geom(
            name="box",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[self.half] * 3,
            mass=self.placement.box_mass,
            rgba=[0.85, 0.7, 0.2, 1],
            condim=3,
        )
        for key, value in self.geom.items():
            setattr(geom, key, value)
        goal = spec.worldbody.add_body(name="goal", mocap=True, pos=[0, 0, 0])
        goal.add_geom(
            name="goal",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.25, 0.25, 0.01],
            rgba=[0.85, 0.15, 0.15, 0.6],
            contype=0,
            conaffinity=0,
        )

    def bind(self, env: EnvView) -> None:
        joint = env.free_joint("box_root")
        self.qpos = joint.qpos
        self.position = joint.qpos[:, :3]
        self.velocity = joint.qvel
        self.marker = env.mocap_pos("goal")
        self.goal = np.zeros((env.num_envs, 3))

    def reset(self, env: EnvView, ids: np.ndarray) -> None:
        arena = self.arena
        obj, goal = self.placement.draw(env.rng, len(ids), arena.half, self.spawn)
        self.qpos[ids, :2] = obj
        self.qpos[ids, 2] = arena.ground(obj, ids) + self.half / arena.cos_slope + 0.01
        self.qpos[ids, 3:7] = arena.tilt
        self.goal[ids] = np.column_stack([goal, arena.ground(goal, ids)])
        self.marker[ids] = self.goal[ids]
