"""Reward terms, each a part a task lists, and every task's weights in one table.

The reward of a step is the sum of its task's terms; each term is reported as a step component
under its name. A term is a pure function of the environment and of the state of the props it
reads (`derl.envs.objects`: they advance it after each step, before any term), so terms keep
nothing and their order does not matter. Distances are of the head centre in the ground plane
unless said otherwise. Each term states how large its episode sum can be (`RewardTerm.
episode_bound`), from its own weights: the bound on a fitness is derived from them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from derl.envs.task import EpisodeLimits, RewardTerm
from derl.envs.view import EnvView

if TYPE_CHECKING:
    from derl.envs.objects import CarriedObject, FloorCells, GoalPoint


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
        velocity = (env.head_pos[:, 0] - env.prev_head[:, 0]) / env.control_dt
        forward = self.weight * velocity
        if self.cos_slope != 1.0:
            forward /= self.cos_slope
        return forward

    def episode_bound(self, limits: EpisodeLimits) -> float:
        """The velocities sum to the distance gained along x in the episode over the control
        step: at most the arena's diagonal over it."""
        return abs(self.weight) * limits.diagonal / limits.control_dt / self.cos_slope


class ReachGoal(RewardTerm):
    """``w_reach (d_prev - d) + bonus [d <= margin]``, d the head-goal distance (`GoalPoint`)."""

    name: ClassVar[str] = "reach"

    def __init__(self, goal: GoalPoint, weights: RewardWeights) -> None:
        self.goal, self.weight, self.bonus = goal, weights.reach, weights.bonus

    def __call__(self, env: EnvView) -> np.ndarray:
        return self.weight * self.goal.gain + self.bonus * self.goal.arrived

    def episode_bound(self, limits: EpisodeLimits) -> float:
        """The gains sum to at most the arena's diagonal; the bonus at most once a step."""
        return abs(self.weight) * limits.diagonal + abs(self.bonus) * limits.steps


class ReachObject(RewardTerm):
    """``w_reach (d_prev - d)`` with d the distance from the nearest of the agent's points to the
    nearest of the object's reach points (`CarriedObject.reach_distance`), plus ``bonus`` the
    first time d <= margin in an episode (the released code, derl/envs/tasks/manipulation.py)."""

    name: ClassVar[str] = "reach"

    def __init__(self, obj: CarriedObject, weights: RewardWeights) -> None:
        self.obj, self.weight, self.bonus = obj, weights.reach, weights.bonus

    def __call__(self, env: EnvView) -> np.ndarray:
        return self.weight * self.obj.reach_gain + self.bonus * self.obj.first_reach

    def episode_bound(self, limits: EpisodeLimits) -> float:
        """The gains sum to at most the arena's diagonal; the bonus once an episode."""
        return abs(self.weight) * limits.diagonal + abs(self.bonus)


class PushObject(RewardTerm):
    """``w_push (d_prev - d) + bonus [d <= margin]`` with d the object-goal distance in the
    ground plane: the bonus at every step the object is within the margin, and the whole term
    zero until the agent has reached the object (`CarriedObject.reached`; the released code)."""

    name: ClassVar[str] = "push"

    def __init__(self, obj: CarriedObject, weights: RewardWeights) -> None:
        self.obj, self.weight, self.bonus = obj, weights.push, weights.bonus

    def __call__(self, env: EnvView) -> np.ndarray:
        obj = self.obj
        return np.where(obj.reached, self.weight * obj.push_gain + self.bonus * obj.delivered, 0.0)

    def episode_bound(self, limits: EpisodeLimits) -> float:
        """The gains sum to at most the arena's diagonal; the bonus at most once a step."""
        return abs(self.weight) * limits.diagonal + abs(self.bonus) * limits.steps


class Explore(RewardTerm):
    """+1 for each square of ``cells`` the head is in for the first time in the episode, the
    first step's square included (`FloorCells.entered`; the released code's
    ExploreTerrainReward)."""

    name: ClassVar[str] = "explore"

    def __init__(self, cells: FloorCells) -> None:
        self.cells = cells

    def __call__(self, env: EnvView) -> np.ndarray:
        return self.cells.entered.astype(np.float64)

    def step_bound(self, limits: EpisodeLimits) -> float:
        return 1.0


class Escape(RewardTerm):
    """The step's gain in distance from the arena's centre (the released escape task's
    ``__reward__forward``, its reported score)."""

    name: ClassVar[str] = "escape"

    def __call__(self, env: EnvView) -> np.ndarray:
        radius = np.linalg.norm(env.head_pos[:, :2], axis=1)
        return radius - np.linalg.norm(env.prev_head[:, :2], axis=1)

    def episode_bound(self, limits: EpisodeLimits) -> float:
        """The gains sum to at most the arena's diagonal."""
        return limits.diagonal


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

    def step_bound(self, limits: EpisodeLimits) -> float:
        return abs(self.bonus)
