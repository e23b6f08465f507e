"""N gymnasium environments behind the `BatchedEnv` interface (for users' envs and tests).

A plain Python loop over the copies: DERL's own environments step all copies in C instead. The
observation is flattened into one type, "proprioception" (normalised, as the original
normalised a non-dict observation whole); the reward is the single component "reward";
actions in [-1, 1] are rescaled to the bounds of the Box action space.
"""

from __future__ import annotations

from typing import Any, cast

import gymnasium
import numpy as np

from derl.rl.env_api import Obs, StepResult

OBS_KEY = "proprioception"


class GymBatchedEnv:
    """`num_envs` copies of `gymnasium.make(env_id, **make_kwargs)`, auto-reset on episode end."""

    def __init__(self, env_id: str, num_envs: int, **make_kwargs: Any) -> None:
        self.envs = [gymnasium.make(env_id, **make_kwargs) for _ in range(num_envs)]
        space = self.envs[0].action_space
        if not isinstance(space, gymnasium.spaces.Box):
            raise TypeError(f"{env_id}: only Box action spaces are supported, got {space}")
        self._low = space.low.astype(np.float64)
        self._half_range = (space.high.astype(np.float64) - self._low) / 2.0
        self.num_envs = num_envs
        self.action_dim = int(np.prod(space.shape))
        self._action_shape = space.shape
        self._obs_space = self.envs[0].observation_space
        self.obs_spaces = {OBS_KEY: int(gymnasium.spaces.flatdim(self._obs_space))}

    def _flat(self, obs: Any) -> np.ndarray:
        # an array: the space is flattenable (`flatdim` checked it)
        flat = cast(np.ndarray, gymnasium.spaces.flatten(self._obs_space, obs))
        return flat.astype(np.float32)

    def reset(self, seed: int) -> Obs:
        """Copy i is reset with seed `seed + i`."""
        rows = [self._flat(env.reset(seed=seed + i)[0]) for i, env in enumerate(self.envs)]
        return {OBS_KEY: np.stack(rows)}

    def step(self, actions: np.ndarray) -> StepResult:
        scaled = self._low + (np.clip(actions, -1.0, 1.0) + 1.0) * self._half_range
        obs = np.empty((self.num_envs, self.obs_spaces[OBS_KEY]), np.float32)
        reward = np.empty(self.num_envs)
        terminated = np.empty(self.num_envs, bool)
        truncated = np.empty(self.num_envs, bool)
        for i, env in enumerate(self.envs):
            o, reward[i], terminated[i], truncated[i], _ = env.step(
                scaled[i].reshape(self._action_shape)
            )
            if terminated[i] or truncated[i]:
                o = env.reset()[0]
            obs[i] = self._flat(o)
        return StepResult(
            obs={OBS_KEY: obs},
            reward=reward,
            terminated=terminated,
            truncated=truncated,
            components={"reward": reward.copy()},
        )

    def close(self) -> None:
        for env in self.envs:
            env.close()
