"""Every task as a standard `gymnasium.Env`, and as a `gymnasium.vector.VectorEnv`, for users
who bring their own learner.

`UnimalGymEnv` is one copy of the batched environment (the same code path as training), with
gymnasium's episode protocol: a finished episode returns its last observation, and the user calls
`reset`. Registered ids (by ``import derl``): ``derl/<Task>-v0`` for every task (e.g.
``derl/FT-v0``, ``derl/Patrol-v0``), episodes of 1,000 steps (the spec's `max_episode_steps`);
``gymnasium.make("derl/VT-v0", genome=Genome | path-to-JSON)``. The observation is a `Dict` of
float32 arrays (``proprioception``, and by task ``heightmap``, ``object``, ``goal``): a learner
that takes one array wants gymnasium's ``FlattenObservation`` wrapper (Stable-Baselines3: its
``MultiInputPolicy`` takes the dict, its ``MlpPolicy`` the flattened one). With
``render_mode="rgb_array"``, `render` returns the frame `derl rollout --video` films (the body
followed by the camera on its dressed set, `derl.envs.video`), so gymnasium's ``RecordVideo``
and ``RenderCollection`` wrappers work (offscreen OpenGL: ``MUJOCO_GL=egl`` or ``osmesa``).

`UnimalVectorEnv` is N copies in one batched simulation, as derl trains
(``gymnasium.make_vec("derl/FT-v0", num_envs=32, vectorization_mode="vector_entry_point",
genome=...)``): one MuJoCo batch steps them all (about twice the env steps/s of gymnasium's
``"sync"`` vectorisation of as many single environments, FT, 8 and 32 copies, on a loaded 2-core
machine). A copy whose episode ends is reset in the same step (gymnasium's ``SAME_STEP``
autoreset): the step returns its new episode's first observation, and the last one in
``info["final_obs"]`` (where ``info["_final_obs"]``). Stable-Baselines3's vector API differs:
examples/stable_baselines3_ft.py adapts one to the other.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from derl.envs.batched import EnvConfig, UnimalEnv
from derl.envs.registry import make_task
from derl.unimal import Genome


class UnimalGymEnv(gymnasium.Env):
    """One UNIMAL in one task; observations are a dict of flat float32 arrays per type."""

    metadata = {"render_modes": ["rgb_array"]}  # noqa: RUF012  (and its "render_fps", below)

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
        self.render_mode, self.size = render_mode, (width, height)
        self.env = UnimalEnv(
            _genome(genome), make_task(task, **task_options), EnvConfig(num_envs=1)
        )
        # a frame per control step: the real-time frame rate
        self.metadata = {**self.metadata, "render_fps": round(1 / self.env.control_dt)}
        self.observation_space, self.action_space = _spaces(self.env)
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


class UnimalVectorEnv(VectorEnv):
    """`num_envs` copies of one UNIMAL in one task, simulated as one batch (`nthread` threads),
    episodes of `max_episode_steps` (the registered spec's: 1,000), with gymnasium's vector API;
    observations a dict of (num_envs, dim) float32 arrays, rewards,
    `terminated` and `truncated` (num_envs,) arrays, the reward's components (e.g. ``forward``)
    as (num_envs,) arrays in the info (see the module for the autoreset)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}  # noqa: RUF012

    def __init__(
        self,
        genome: Genome | str | Path,
        task: str,
        num_envs: int = 32,
        nthread: int = 1,
        max_episode_steps: int | None = None,
        **task_options: Any,
    ) -> None:
        steps = {} if max_episode_steps is None else {"episode_steps": max_episode_steps}
        config = EnvConfig(num_envs=num_envs, nthread=nthread, **steps)
        self.env = UnimalEnv(_genome(genome), make_task(task, **task_options), config)
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = _spaces(self.env)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        return self.env.reset(int(self.np_random.integers(2**31))), {}

    def step(
        self, actions: np.ndarray
    ) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        result = self.env.step(np.asarray(actions, dtype=np.float32))
        every = np.ones(self.num_envs, dtype=bool)
        info: dict[str, Any] = {}
        for key, value in result.components.items():
            info[key], info[f"_{key}"] = value, every
        ended = (result.terminated | result.truncated).nonzero()[0]
        if len(ended):
            final = np.full(self.num_envs, None, dtype=object)
            for i in ended:
                final[i] = {key: value[i] for key, value in result.final_obs.items()}
            info["final_obs"], info["_final_obs"] = final, result.terminated | result.truncated
        return result.obs, result.reward, result.terminated, result.truncated, info


def gym_id(task: str) -> str:
    """The id `import derl` registered `task` under (`derl.register_gym_envs`), as gymnasium's
    registry holds it; KeyError where it holds none."""
    for spec in gymnasium.registry.values():
        if spec.namespace == "derl" and (spec.kwargs or {}).get("task") == task:
            return spec.id
    raise KeyError(f"no gymnasium id for task {task!r}")


def _genome(genome: Genome | str | Path) -> Genome:
    """A genome, or the one of a JSON file."""
    if isinstance(genome, Genome):
        return genome
    return Genome.model_validate_json(Path(genome).read_text())


def _spaces(env: UnimalEnv) -> tuple[spaces.Dict, spaces.Box]:
    """One copy's observation space (a dict of flat float32 arrays) and action space."""
    observations = spaces.Dict(
        {
            key: spaces.Box(-np.inf, np.inf, (size,), np.float32)
            for key, size in env.obs_spaces.items()
        }
    )
    return observations, spaces.Box(-1.0, 1.0, (env.action_dim,), np.float32)
