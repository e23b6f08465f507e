"""Vectorised episode bookkeeping during training, the learning curve and the fitness from it.

Per copy, running sums of the reward and of every reward component plus the episode length; when
copies finish, one record per episode (env step at finish, return, component sums, length) is
appended for all of them at once. At the end of every iteration, once two episodes have finished,
the curve gets the mean fitness-component sum of the last `recent` finished episodes (the released
code's per-iteration value); the fitness is the mean of the curve's values in the last window of
steps (the released code's: its last 100 of 1220 values; `derl.lifetime.fitness_window`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

FitnessSource = Literal["window", "last_episodes", "unfinished"]


@dataclass(frozen=True)
class EpisodeLog:
    """Finished episodes in order of finishing; every array has one entry per episode."""

    finish_step: np.ndarray
    """Env steps (all copies) done when the episode finished."""
    ret: np.ndarray
    """Sum of the raw (unscaled) reward."""
    length: np.ndarray
    components: dict[str, np.ndarray]
    """Sum of each reward component."""

    def __len__(self) -> int:
        return len(self.finish_step)


@dataclass(frozen=True)
class Fitness:
    """Mean episode sum of one reward component, and where it came from.

    `source` is "window" (the mean of the curve's values of the iterations in the last window of
    steps, the definition; `episodes`: the finished episodes those values average), else
    "last_episodes" (a single episode finished: its sum), or "unfinished" (none did: the partial
    sums of the episodes still running).
    """

    value: float
    source: FitnessSource
    episodes: int


class EpisodeTracker:
    """Running per-copy sums; records every episode that finishes."""

    def __init__(self, num_envs: int, component: str, recent: int) -> None:
        self.component = component
        self.ret = np.zeros(num_envs)
        self.length = np.zeros(num_envs, np.int64)
        self.sums: dict[str, np.ndarray] = {}
        self.recent: deque[float] = deque(maxlen=recent)
        self.recent_ret: deque[float] = deque(maxlen=recent)  # their raw-reward sums
        self.recent_length: deque[int] = deque(maxlen=recent)  # their lengths
        self._finish: list[np.ndarray] = []
        self._ret: list[np.ndarray] = []
        self._length: list[np.ndarray] = []
        self._components: dict[str, list[np.ndarray]] = {}
        self.curve: list[tuple[int, float]] = []
        """Per iteration once two episodes have finished: (env steps, `recent_mean()`)."""
        self._finished: list[int] = []  # per curve point: episodes finished by then
        self.count = 0  # episodes finished so far

    def step(
        self,
        reward: np.ndarray,
        components: dict[str, np.ndarray],
        done: np.ndarray,
        env_steps: int,
    ) -> None:
        """Add one batched step; `env_steps` counts all copies' steps including this one."""
        if not self.sums:
            if self.component not in components:
                raise KeyError(
                    f"fitness component {self.component!r} not among the environment's reward "
                    f"components {sorted(components)}"
                )
            self.sums = {key: np.zeros_like(self.ret) for key in components}
            self._components = {key: [] for key in components}
        self.ret += reward
        self.length += 1
        for key, value in components.items():
            self.sums[key] += value
        idx = np.flatnonzero(done)
        if idx.size == 0:
            return
        self._finish.append(np.full(idx.size, env_steps, np.int64))
        self._ret.append(self.ret[idx])
        self._length.append(self.length[idx])
        for key, running in self.sums.items():
            self._components[key].append(running[idx])
            running[idx] = 0.0
        self.recent.extend(self._components[self.component][-1])
        self.recent_ret.extend(self.ret[idx].tolist())
        self.recent_length.extend(self.length[idx].tolist())
        self.count += idx.size
        self.ret[idx] = 0.0
        self.length[idx] = 0

    def end_iteration(self, env_steps: int) -> float | None:
        """Close an iteration: its curve point, once two episodes have finished (the released
        code's condition), which it returns; None before."""
        if self.count < 2:
            return None
        value = self.recent_mean()
        self.curve.append((env_steps, value))
        self._finished.append(self.count)
        return value

    def recent_mean(self) -> float:
        """Mean fitness-component sum over the last `recent` finished episodes (some finished)."""
        return float(np.mean(self.recent))

    def recent_episodes(self) -> tuple[float | None, float | None]:
        """Mean raw-reward sum and mean length (control steps) of the last `recent` finished
        episodes (Stable-Baselines3's ep_rew_mean and ep_len_mean); None before one finished."""
        if not self.recent_ret:
            return None, None
        return float(np.mean(self.recent_ret)), float(np.mean(self.recent_length))

    def log(self) -> EpisodeLog:
        def cat(parts: list[np.ndarray], dtype: type) -> np.ndarray:
            return np.concatenate(parts) if parts else np.zeros(0, dtype)

        return EpisodeLog(
            finish_step=cat(self._finish, np.int64),
            ret=cat(self._ret, np.float64),
            length=cat(self._length, np.int64),
            components={k: cat(v, np.float64) for k, v in self._components.items()},
        )

    def state_dict(self) -> dict[str, Any]:
        """Everything recorded and running, as arrays and lists (a training resumed goes on
        from it: `load_state_dict`)."""
        log = self.log()
        return {
            "ret": self.ret.copy(),
            "length": self.length.copy(),
            "sums": {key: value.copy() for key, value in self.sums.items()},
            "recent": [float(value) for value in self.recent],
            "finish": log.finish_step,
            "returns": log.ret,
            "lengths": log.length,
            "components": log.components,
            "curve": [list(point) for point in self.curve],
            "finished": list(self._finished),
            "count": self.count,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.ret = np.array(state["ret"], np.float64)
        self.length = np.array(state["length"], np.int64)
        self.sums = {key: np.array(value, np.float64) for key, value in state["sums"].items()}
        self.recent.clear()
        self.recent.extend(state["recent"])
        returns, lengths = np.asarray(state["returns"]), np.asarray(state["lengths"])
        first = len(returns) - len(self.recent)  # the episodes `recent` holds, last finished
        self.recent_ret.clear()
        self.recent_ret.extend(returns[first:].astype(np.float64).tolist())
        self.recent_length.clear()
        self.recent_length.extend(lengths[first:].astype(np.int64).tolist())
        self._finish = [np.array(state["finish"], np.int64)]
        self._ret = [np.array(state["returns"], np.float64)]
        self._length = [np.array(state["lengths"], np.int64)]
        self._components = {
            key: [np.array(value, np.float64)] for key, value in state["components"].items()
        }
        self.curve = [(int(steps), float(value)) for steps, value in state["curve"]]
        self._finished = list(state["finished"])
        self.count = int(state["count"])

    def fitness(self, env_steps: int, window: int) -> Fitness:
        """Mean of the curve's values of the iterations that ended in the last `window` steps
        (`env_steps`: the steps done, the last curve point's)."""
        if self.curve:
            steps = np.array([point[0] for point in self.curve])
            first = int(np.searchsorted(steps, env_steps - window, side="right"))
            values = [value for _, value in self.curve[first:]]
            # the first value averages the `recent` episodes finished last by its iteration
            recent = self.recent.maxlen
            assert recent is not None  # made with one
            episodes = self._finished[-1] - max(0, self._finished[first] - recent)
            return Fitness(float(np.mean(values)), "window", episodes)
        log = self.log()
        if len(log):
            return Fitness(float(log.components[self.component].mean()), "last_episodes", len(log))
        return Fitness(float(self.sums[self.component].mean()), "unfinished", 0)
