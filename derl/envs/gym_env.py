"""Every task as a standard `gymnasium.Env`, for users who bring their own learner.

It is one copy of the batched environment (the same code path as training), with gymnasium's
episode protocol: a finished episode returns its last observation, and the user calls `reset`.
Registered ids: ``derl/<Task>-v0`` for every task (e.g. ``derl/FT-v0``, ``derl/Patrol-v0``);
``gymnasium.make("derl/VT-v0", genome=Genome | path-to-JSON)``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from derl.envs.batched import EnvConfig, UnimalEnv
from derl.envs.registry import TASKS, make_task
from derl.unimal import Genome


class UnimalGymEnv(gymnasium.Env):
    """One UNIMAL in one task; observations are a dict of flat float32 arrays per type."""

    metadata = {"render_modes": []}  # noqa: RUF012 (gymnasium's convention)

    def __init__(self, genome: Genome | str | Path, task: str, **task_options: Any) -> None:
        if not isinstance(genome, Genome):
            genome = Genome.model_validate_json(Path(genome).read_text())
        self.env = UnimalEnv(genome, make_task(task, **task_options), EnvConfig(num_envs=1))
        self.observation_space = spaces.Dict(
            {
                key: spaces.Box(-np.inf, np.inf, (size,), np.float32)
                for key, size in self.env.obs_spaces.items()
            }
        )
        self.action_space = spaces.Box(-1.0, 1.0, (self.env.action_dim,), np.float32)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        obs = self.env.reset(int(self.np_random.integers(2**31)))
        return {key: value[0] for key, value in obs.items()}, {}

    def step(
        self, action: np.ndarray
    ) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        result = self.env.step(np.asarray(action, dtype=np.float32)[None])
        terminated, truncated = bool(result.terminated[0]), bool(result.truncated[0])
        obs = result.final_obs if terminated or truncated else result.obs
        info = {key: float(value[0]) for key, value in result.components.items()}
        return (
            {k: v[0] for k, v in obs.items()},
            float(result.reward[0]),
            terminated,
            truncated,
            info,
        )


def register_all() -> None:
    """Register ``derl/<Task>-v0`` for every task (idempotent)."""
    for name in TASKS:
        env_id = f"derl/{make_task(name).gym_name}-v0"
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point=UnimalGymEnv, kwargs={"task": name})
