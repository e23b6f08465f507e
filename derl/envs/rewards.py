"""Reward terms, each a part a task lists, and every task's weights in one table.

The reward of a step is the sum of its task's terms; each term is reported as a step component
under its name. Distances are of the head centre in the ground plane unless said otherwise.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from derl.envs.task import RewardTerm
from derl.envs.view import EnvView

if TYPE_CHECKING:
    from derl.envs.objects import CarriedObject, GoalPoint

CONTROL_DT = 0.02  # s per control step: 4 x 5 ms


class RewardWeights(BaseModel):
    """Weights of the reward terms; ``margin`` (m) is how close counts as arrived."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    forward: float = 1.0
    ctrl: float = Field(1e-3, ge=0)
    reach: float = 100.0
    push: float = 100.0
    bonus: float = 10.0
    margin: float = Field(0.75, gt=0)


REWARD_WEIGHTS: dict[str, RewardWeights] = {
    # the evolution worlds (appendix A)
    "ft": RewardWeights(),
    "vt": RewardWeights(),
    "mvt": RewardWeights(),
    # the test tasks (appendix C)
    "patrol": RewardWeights(margin=0.5),
    "point_nav": RewardWeights(margin=0.5),
    "obstacle": RewardWeights(),
    "exploration": RewardWeights(),
    "escape": RewardWeights(bonus=100.0),
    "incline": RewardWeights(),
    "push_box_incline": RewardWeights(margin=0.5),  # SUCCESS_MARGIN's default in the released
    "manipulate_ball": RewardWeights(margin=0.5),  # code: their configs do not set it
}
"""Each task's weights (a task's factory takes others as its ``weights`` option)."""


class Ctrl(RewardTerm):
    """``-w_c |a|^2`` over the actions as the policy gave them, unclipped (the released code:
    MuJoCo clamps the control it applies to [-1, 1])."""

    name: ClassVar[str] = "ctrl"

    def __init__(self, weights: RewardWeights) -> None:
        self.weight = weights.ctrl

    def __call__(self, env: EnvView) -> np.ndarray:
        return -self.weight * np.add.reduce(np.square(env.action), axis=1)


class Forward(RewardTerm):
    """``w_x v_x``: the head's x velocity over the step (its episode sum is 50 x the distance
    along +x); on a slope, divided by ``cos_slope``: the speed along it."""

    name: ClassVar[str] = "forward"

    def __init__(self, weights: RewardWeights, cos_slope: float = 1.0) -> None:
        self.weight = weights.forward
        self.cos_slope = cos_slope

    def __call__(self, env: EnvView) -> np.ndarray:
        velocity = (env.head_pos[:, 0] - env.prev_head[:, 0]) / CONTROL_DT
        forward = self.weight * velocity
        if self.cos_slope != 1.0:
            forward /= self.cos_slope
        return forward


class ReachGoal(RewardTerm):
    """``w_reach (d_prev - d) + bonus [d <= margin]``, d the head-goal distance (`GoalPoint`)."""

    name: ClassVar[str] = "reach"

    def __init__(self, goal: GoalPoint, weights: RewardWeights) -> None:
        self.goal, self.weight, self.bonus = goal, weights.reach, weights.bonus

    def __call__(self, env: EnvView) -> np.ndarray:
        return self.weight * self.goal.gain + self.bonus * self.goal.arrived


class ReachObject(RewardTerm):
    """``w_reach (d_prev - d)`` with d the distance from the nearest of the agent's points (head
    centre and bottom, limb middles and ends) to the nearest of the object's reach points
    (`CarriedObject.reach_points`), plus ``bonus`` the first time d <= margin in an episode,
    after which `reached` is set (the released code, derl/envs/tasks/manipulation.py)."""

    name: ClassVar[str] = "reach"

    def __init__(self, obj: CarriedObject, weights: RewardWeights) -> None:
        self.obj, self.weights = obj, weights

    def bind(self, env: EnvView) -> None:
        self.dist = np.zeros(env.num_envs)
        self.reached = np.zeros(env.num_envs, dtype=bool)

    def distance(self, env: EnvView) -> np.ndarray:
        points, targets = env.agent_points(), self.obj.reach_points()
        gaps = points[:, :, None] - targets[:, None]  # (N, P, K, 3)
        squares = np.add.reduce(np.square(gaps, out=gaps), axis=3).reshape(len(gaps), -1)
        return np.sqrt(np.minimum.reduce(squares, axis=1))

    def placed(self, env: EnvView, ids: np.ndarray) -> None:
        self.dist[ids] = self.distance(env)[ids]
        self.reached[ids] = False

    def __call__(self, env: EnvView) -> np.ndarray:
        w, dist = self.weights, self.distance(env)
        now = ~self.reached & (dist <= w.margin)
        term = w.reach * (self.dist - dist) + w.bonus * now
        self.dist = dist
        self.reached |= now
        return term


class PushObject(RewardTerm):
    """``w_push (d_prev - d) + bonus [d <= margin]`` with d the object-goal distance in the
    ground plane: the bonus at every step the object is within the margin, and the whole term
    zero until ``reach`` has `reached` the object (the released code; list ``reach`` before
    this term)."""

    name: ClassVar[str] = "push"

    def __init__(self, obj: CarriedObject, weights: RewardWeights, reach: ReachObject) -> None:
        self.obj, self.weights, self.reach = obj, weights, reach

    def bind(self, env: EnvView) -> None:
        self.dist = np.zeros(env.num_envs)

    def distance(self) -> np.ndarray:
        gap = self.obj.position[:, :2] - self.obj.goal[:, :2]
        return np.hypot(gap[:, 0], gap[:, 1])

    def placed(self, env: EnvView, ids: np.ndarray) -> None:
        self.dist[ids] = self.distance()[ids]

    def __call__(self, env: EnvView) -> np.ndarray:
        w, dist = self.weights, self.distance()
        term = w.push * (self.dist - dist) + w.bonus * (dist <= w.margin)
        self.dist = dist
        return np.where(self.reach.reached, term, 0.0)


class Explore(RewardTerm):
    """+1 for each ``cell`` x ``cell`` square of a floor of half size ``half`` that the head is
    in for the first time in the episode, the first step's square included (the released
    code's ExploreTerrainReward)."""

    name: ClassVar[str] = "explore"

    def __init__(self, half: float, cell: float) -> None:
        self.half, self.cell = half, cell
        self.cells = round(2 * half / cell)

    def bind(self, env: EnvView) -> None:
        self.visited = np.zeros((env.num_envs, self.cells, self.cells), dtype=bool)
        self.copies = np.arange(env.num_envs)

    def _cell(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(column, row) of the cell under each point; points off the floor count as its edge."""
        index = np.floor((xy + self.half) / self.cell).astype(np.intp)
        index = np.clip(index, 0, self.cells - 1)
        return index[:, 0], index[:, 1]

    def placed(self, env: EnvView, ids: np.ndarray) -> None:
        self.visited[ids] = False

    def __call__(self, env: EnvView) -> np.ndarray:
        col, row = self._cell(env.head_pos[:, :2])
        new = ~self.visited[self.copies, row, col]
        self.visited[self.copies, row, col] = True
        return new.astype(np.float64)


class Escape(RewardTerm):
    """The step's gain in distance from the arena's centre (the released escape task's
    ``__reward__forward``, its reported score)."""

    name: ClassVar[str] = "escape"

    def __call__(self, env: EnvView) -> np.ndarray:
        radius = np.linalg.norm(env.head_pos[:, :2], axis=1)
        return radius - np.linalg.norm(env.prev_head[:, :2], axis=1)


class RimBonus(RewardTerm):
    """``bonus`` at the step the head is ``rim`` m or further from the arena's centre (the
    released code's `TerminateOnEscape`, which adds it to the reward and to no reported
    component)."""

    name: ClassVar[str] = "rim"

    def __init__(self, rim: float, weights: RewardWeights) -> None:
        self.rim, self.bonus = rim, weights.bonus

    def __call__(self, env: EnvView) -> np.ndarray:
        radius = np.linalg.norm(env.head_pos[:, :2], axis=1)
        return self.bonus * (radius >= self.rim)
