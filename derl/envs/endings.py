"""Success tests: episodes a task ends because it is achieved (the environment's own endings,
falls, the arena's edge, the time limit and unstable physics, apply to every task)."""

from __future__ import annotations

import numpy as np

from derl.envs.task import Success
from derl.envs.view import EnvView


class Escaped(Success):
    """The head is ``rim`` m or further from the arena's centre (in the ground plane)."""

    def __init__(self, rim: float) -> None:
        self.rim = rim

    def __call__(self, env: EnvView) -> np.ndarray:
        return np.linalg.norm(env.head_pos[:, :2], axis=1) >= self.rim
