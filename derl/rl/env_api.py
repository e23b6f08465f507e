"""The batched-environment interface the PPO trainer consumes.

N copies of one environment are stepped together with numpy arrays in and out. Finished copies
reset themselves inside `step`. Environment classes conform structurally (`typing.Protocol`), so
they never import this package. An environment may also count the seconds it spends in its
physics engine in a `physics_s` attribute; the trainer then reports them (`TimeSplit.physics_s`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

Obs = dict[str, np.ndarray]
"""Observation type name -> (N, dim) float32 array."""


@dataclass(frozen=True)
class StepResult:
    """What one batched step returns; every array has the copies on its first axis (N)."""

    obs: Obs
    """Observations after the step, already reset for the copies that finished."""
    reward: np.ndarray
    """(N,) float reward."""
    terminated: np.ndarray
    """(N,) bool: the episode ended in a terminal state (no bootstrapping)."""
    truncated: np.ndarray
    """(N,) bool: the episode hit its time limit, terminated or not (this step's advantage is 0
    and its value target its own value, the released code's)."""
    components: dict[str, np.ndarray]
    """Per-step reward components, each (N,) float, e.g. "forward", "ctrl", "energy"."""


class Step(Protocol):
    """What `BatchedEnv.step` returns: a `StepResult`, or an environment's own class with its
    fields (structurally, as the environments themselves; e.g. `derl.envs.StepResult`)."""

    @property
    def obs(self) -> Obs: ...

    @property
    def reward(self) -> np.ndarray: ...

    @property
    def terminated(self) -> np.ndarray: ...

    @property
    def truncated(self) -> np.ndarray: ...

    @property
    def components(self) -> dict[str, np.ndarray]: ...


@runtime_checkable
class BatchedEnv(Protocol):
    """N copies of one environment stepped together, with auto-reset."""

    @property
    def num_envs(self) -> int:
        """Number of copies N."""
        ...

    @property
    def obs_spaces(self) -> dict[str, int]:
        """Observation type name -> flat dimension, e.g. {"proprioception": 50}."""
        ...

    @property
    def action_dim(self) -> int:
        """Action size A; actions are applied within [-1, 1]."""
        ...

    def reset(self, seed: int) -> Obs:
        """Reset every copy (deterministically for a given seed) and return the observations."""
        ...

    def step(self, actions: np.ndarray) -> Step:
        """Apply (N, A) float32 actions to all copies: the policy's samples, unclipped; the
        environment clips them to [-1, 1] where it applies them."""
        ...
