"""Props: what a task puts in its arena each episode, and the episode's record of it. `GoalPoint`
is a goal for the head; `CarriedObject` is a free body (a box, or a ball) and the goal marker it is
to be brought to; `FloorCells` are the squares of a floor the head has been in. Each advances its
state after every step, before the reward terms, observations and success tests read it."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Protocol

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from derl.envs.flat_ground import OBJECT_BIT
from derl.envs.task import Arena, Part
from derl.envs.view import EnvView
from derl.unimal.mjcf import FRICTION

Draw = Callable[[np.random.Generator, int], np.ndarray]

GOAL_LIFT = 0.11  # m: a goal's centre above the ground (the released code's goal marker)
FACES = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64
)  # a cube's face centres, in half sides


class GoalPoint(Part):
    """A goal on the ground: ``draw(rng, n)`` gives (n, 2) positions for n new episodes. After
    each step, ``gain`` is the decrease in head-goal distance (xy) and ``arrived`` whether the
    head is within ``margin``; with ``alternate``, an arrival mirrors the goal's x (patrol).
    The goal's centre is ``lift`` m above the (flat) floor: only its observation sees that."""

    def __init__(
        self, draw: Draw, margin: float, alternate: bool = False, lift: float = GOAL_LIFT
    ) -> None:
        self.draw, self.margin, self.alternate, self.lift = draw, margin, alternate, lift

    def bind(self, env: EnvView) -> None:
        n = env.num_envs
        self.goal = np.zeros((n, 3))
        self.goal[:, 2] = self.lift
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


class ForwardPlacement(BaseModel):
    """The released code's ``forward_placement`` (derl/utils/placement.py): the object a whole
    number of metres ``ahead`` (inclusive) of the spawn along +x, its goal as far again beyond
    it; each x capped ``far_buffer`` m plus its half size before the far edge, each y uniform
    with ``side_buffer`` m plus its half size kept free along the sides; a goal whose footprint
    overlaps the object's is redrawn (up to 10 times, as the released code's placement grid)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    ahead: tuple[int, int] = (15, 24)  # FORWARD_PLACEMENT_DIST [15, 25): randint
    side_buffer: float = Field(10.0, ge=0)  # 2 x PLACEMENT_BUFFER_WIDTH (grid cells are 2 per m)
    far_buffer: float = Field(6.0, ge=0)  # 2 x PLACEMENT_BUFFER_LEN
    goal_half: float = Field(0.5, gt=0)  # the goal marker's footprint half size

    if TYPE_CHECKING:  # each subclass's field or property (`ObjectPlacement`)

        @property
        def box_size(self) -> float: ...

    @property
    def object_half(self) -> float:
        """Half the object's height (`box_size`, given by the placement of each object)."""
        return self.box_size / 2

    def draw(
        self,
        rng: np.random.Generator,
        n: int,
        half: tuple[float, float],
        spawn: tuple[float, float],
    ) -> tuple[np.ndarray, np.ndarray]:
        low, high = self.ahead
        obj_half, goal_half = self.object_half, self.goal_half
        x_far = half[0] - self.far_buffer
        y_obj, y_goal = (half[1] - self.side_buffer - h for h in (obj_half, goal_half))
        if min(y_obj, y_goal) < 0 or x_far - goal_half < spawn[0]:
            raise ValueError(f"an arena of half size {half} leaves no room for {self}")
        obj_x = np.minimum(spawn[0] + rng.integers(low, high + 1, n), x_far - obj_half)
        goal_x = np.minimum(obj_x + rng.integers(low, high + 1, n), x_far - goal_half)
        obj_y = rng.uniform(-y_obj, y_obj, n)
        goal_y = rng.uniform(-y_goal, y_goal, n)
        reach = obj_half + goal_half
        for _ in range(9):
            overlap = (np.abs(goal_x - obj_x) < reach) & (np.abs(goal_y - obj_y) < reach)
            if not overlap.any():
                break
            goal_y[overlap] = rng.uniform(-y_goal, y_goal, np.count_nonzero(overlap))
        return np.column_stack([obj_x, obj_y]), np.column_stack([goal_x, goal_y])


class CarriedObject(Part):
    """A cube (body "box", free joint "box_root", geom "box"; ``geom`` overrides attributes of
    the geom, e.g. to make it a ball) resting on ``arena`` where ``placement`` says, and a goal
    marker (mocap body "goal") `GOAL_LIFT` m above the ground. `position` is the object's live
    (N, 3) centre, `velocity` its (N, 6) free-joint velocity (linear in the world frame, angular
    in the object's own frame, MuJoCo's convention), `goal` (N, 3) its goals. ``faces``: the
    agent reaches the cube at its six face centres (else at its centre, as for a ball).

    After each step: `reach_gain` is the decrease in the agent-object distance
    (`reach_distance`), `reached` whether that distance has been within ``margin`` in the
    episode and `first_reach` whether it came within it at this step for the first time;
    `push_gain` is the decrease in the object-goal distance (`goal_distance`) and `delivered`
    whether that distance is within ``margin``."""

    def __init__(
        self,
        arena: Arena,
        spawn: tuple[float, float],
        placement: ObjectPlacement,
        margin: float,
        geom: Mapping[str, object] | None = None,
        faces: bool = True,
    ) -> None:
        self.arena, self.spawn, self.placement, self.margin = arena, spawn, placement, margin
        self.geom = dict(geom or {})
        self.faces = faces
        self.half = placement.box_size / 2
        self._face_offsets = FACES.T * self.half  # (3, 6): columns are face centres, body frame

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
            friction=list(FRICTION),  # the released unimal.xml's default geom class
            contype=OBJECT_BIT,
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
        self.rot = joint.rot
        self.velocity = joint.qvel
        self.marker = env.mocap_pos("goal")
        n = env.num_envs
        self.goal = np.zeros((n, 3))
        self.reach_dist, self.goal_dist = np.zeros(n), np.zeros(n)
        self.reached = np.zeros(n, dtype=bool)

    def reset(self, env: EnvView, ids: np.ndarray) -> None:
        arena = self.arena
        obj, goal = self.placement.draw(env.rng, len(ids), arena.half, self.spawn)
        self.qpos[ids, :2] = obj
        self.qpos[ids, 2] = arena.top(obj, self.half, ids) + self.half / arena.cos_slope
        self.qpos[ids, 3:7] = arena.tilt
        self.goal[ids] = np.column_stack([goal, arena.ground(goal, ids) + GOAL_LIFT])
        self.marker[ids] = self.goal[ids]

    def placed(self, env: EnvView, ids: np.ndarray) -> None:
        self.reach_dist[ids] = self.reach_distance(env)[ids]
        self.reached[ids] = False
        self.goal_dist[ids] = self.goal_distance()[ids]

    def update(self, env: EnvView) -> None:
        reach = self.reach_distance(env)
        self.reach_gain = self.reach_dist - reach
        self.first_reach = ~self.reached & (reach <= self.margin)
        self.reached |= self.first_reach
        self.reach_dist = reach
        goal = self.goal_distance()
        self.push_gain = self.goal_dist - goal
        self.delivered = goal <= self.margin
        self.goal_dist = goal

    def reach_distance(self, env: EnvView) -> np.ndarray:
        """(N,) the distance from the nearest of the agent's points (head centre and bottom, limb
        middles and ends) to the nearest of the object's `reach_points`."""
        points, targets = env.agent_points(), self.reach_points()
        gaps = points[:, :, None] - targets[:, None]  # (N, P, K, 3)
        squares = np.add.reduce(np.square(gaps, out=gaps), axis=3).reshape(len(gaps), -1)
        return np.sqrt(np.minimum.reduce(squares, axis=1))

    def goal_distance(self) -> np.ndarray:
        """(N,) the object-goal distance in the ground plane."""
        gap = self.position[:, :2] - self.goal[:, :2]
        return np.hypot(gap[:, 0], gap[:, 1])

    def angular_velocity(self) -> np.ndarray:
        """(N, 3) the object's angular velocity in the world frame."""
        return np.matmul(self.rot, self.velocity[:, 3:6, None])[:, :, 0]

    def reach_points(self) -> np.ndarray:
        """(N, K, 3) where the agent reaches the object: its face centres, or its centre."""
        if not self.faces:
            return self.position[:, None]
        faces = np.matmul(self.rot, self._face_offsets).transpose(0, 2, 1)
        faces += self.position[:, None]
        return faces


class FloorCells(Part):
    """The ``cell`` x ``cell`` squares of a floor of half size ``half`` that the head has been in
    during the episode (a point off the floor counts as in a square at its edge). After each
    step, `entered` is whether the head is in a square for the first time in the episode, the
    first step's square included."""

    def __init__(self, half: float, cell: float) -> None:
        self.half, self.cell = half, cell
        self.cells = round(2 * half / cell)

    def bind(self, env: EnvView) -> None:
        self.visited = np.zeros((env.num_envs, self.cells, self.cells), dtype=bool)
        self.copies = np.arange(env.num_envs)

    def placed(self, env: EnvView, ids: np.ndarray) -> None:
        self.visited[ids] = False

    def update(self, env: EnvView) -> None:
        col, row = self._cell(env.head_pos[:, :2])
        self.entered = ~self.visited[self.copies, row, col]
        self.visited[self.copies, row, col] = True

    def _cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(column, row) of the square under each point."""
        index = np.floor((xy + self.half) / self.cell).astype(np.intp)
        index = np.clip(index, 0, self.cells - 1)
        return index[:, 0], index[:, 1]
