"""Every task as a standard `gymnasium.Env`, for users who bring their own learner.

It is one copy of the batched environment (the same code path as training), with gymnasium's
episode protocol: a finished episode returns its last observation, and the user calls `reset`.
Registered ids (by ``import derl``): ``derl/<Task>-v0`` for every task (e.g. ``derl/FT-v0``,
``derl/Patrol-v0``); ``gymnasium.make("derl/VT-v0", genome=Genome | path-to-JSON)``. With
``render_mode="rgb_array"``, `render` returns the frame `derl rollout --video` films (the body
followed by the camera on its dressed set, `derl.envs.video`), so gymnasium's ``RecordVideo``
and ``RenderCollection`` wrappers work (offscreen OpenGL: ``MUJOCO_GL=egl`` or ``osmesa``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from derl.envs.batched import EnvConfig, UnimalEnv
from derl.envs.registry import make_task
from derl.unimal import Genome

CONTROL_HZ = 50
"""Control steps per second of simulated time (20 ms each): a video's real-time frame rate."""


class UnimalGymEnv(gymnasium.Env):
    """One UNIMAL in one task; observations are a dict of flat float32 arrays per type."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}  # noqa: RUF012

    def __init__(
        self,
        genome: Genome | str | Path,
        task: str,
        render_mode: str | None = None,
        width: int = 480,
        height: int = 360,
        **task_options: Any,
    ) -> None:
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode {render_mode!r}: derl renders only 'rgb_array'")
        if not isinstance(genome, Genome):
            genome = Genome.model_validate_json(Path(genome).read_text())
        self.render_mode, self.size = render_mode, (width, height)
        self.env = UnimalEnv(genome, make_task(task, **task_options), EnvConfig(num_envs=1))
        self.observation_space = spaces.Dict(
            {
                key: spaces.Box(-np.inf, np.inf, (size,), np.float32)
                for key, size in self.env.obs_spaces.items()
            }
        )
        self.action_space = spaces.Box(-1.0, 1.0, (self.env.action_dim,), np.float32)
        self._recorder: Any = None  # derl.envs.video.FrameRecorder, made on the first render

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

    def render(self) -> np.ndarray | None:
        """The body now, (height, width, 3) RGB, with ``render_mode="rgb_array"`` (else None)."""
        if self.render_mode is None:
            return None
        if self._recorder is None:
            from derl.envs.video import FrameRecorder  # OpenGL: only once a frame is wanted

            self._recorder = FrameRecorder(self.env, *self.size)
        return self._recorder.frame()

    def close(self) -> None:
        if self._recorder is not None:
            self._recorder.close()
            self._recorder = None
        super().close()


def register_all() -> None:
    """Register ``derl/<Task>-v0`` for every task (idempotent): what ``import derl`` does."""
    from derl import register_gym_envs

    register_gym_envs()
