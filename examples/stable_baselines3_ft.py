"""Train a derl body with Stable-Baselines3's PPO on derl's batched simulation.

    pip install 'derl[bench]'                                  # Stable-Baselines3
    MUJOCO_GL=egl python examples/stable_baselines3_ft.py bodies/unimal_0000.json [STEPS]

`import derl` registers every task as ``derl/<Task>-v0``. ``gymnasium.make`` gives one copy of
the simulation (a gymnasium ``Env``); ``gymnasium.make_vec(..., vectorization_mode=
"vector_entry_point")`` gives N copies simulated as one batch, as derl trains
(`derl.envs.gym_env.UnimalVectorEnv`, a gymnasium ``VectorEnv``; about twice the env steps/s of
gymnasium's ``"sync"`` vectorisation of N single copies). Stable-Baselines3 has its own vector
API, so `DerlVecEnv` below adapts the one to the other (copy it into your code). The
observations are a dict of float32 arrays (``proprioception``, and by task ``heightmap``,
``object``, ``goal``): Stable-Baselines3's ``MultiInputPolicy`` takes them. The reward is the
task's, and ``info["forward"]`` the fitness term of each step (FT and VT: 50 per metre forward
in an episode). bench/peers.py runs Stable-Baselines3 with the paper's settings beside derl's
own PPO.
"""

import sys
from typing import Any

import gymnasium
import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv

import derl  # noqa: F401 (registers derl/FT-v0 and the other tasks)


class DerlVecEnv(VecEnv):
    """A gymnasium ``VectorEnv`` that resets a copy in the step its episode ends (derl's:
    ``info["final_obs"]`` holds the last observation) as a Stable-Baselines3 ``VecEnv``."""

    def __init__(self, env: gymnasium.vector.VectorEnv) -> None:
        self.env = env
        super().__init__(env.num_envs, env.single_observation_space, env.single_action_space)

    def reset(self) -> dict[str, np.ndarray]:
        obs, _ = self.env.reset(seed=self._seeds[0])
        self._reset_seeds()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self.actions = actions

    def step_wait(self) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, list[dict]]:
        obs, reward, terminated, truncated, info = self.env.step(self.actions)
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for key, values in info.items():
            if not key.startswith("_") and key != "final_obs":
                for i, value in enumerate(values):
                    infos[i][key] = value
        for i in (terminated | truncated).nonzero()[0]:
            infos[i]["terminal_observation"] = info["final_obs"][i]
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return obs, reward.astype(np.float32), terminated | truncated, infos

    def close(self) -> None:
        self.env.close()

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self.env, attr_name)] * len(self._get_indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self.env, attr_name, value)

    def env_method(self, method_name: str, *args: Any, indices: Any = None, **kwargs: Any) -> list:
        return [getattr(self.env, method_name)(*args, **kwargs)] * len(self._get_indices(indices))

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False] * len(self._get_indices(indices))


genome, steps = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 100_000
copies = gymnasium.make_vec("derl/FT-v0", num_envs=8, vectorization_mode="vector_entry_point",
                            genome=genome)  # fmt: skip
env = DerlVecEnv(copies)
model = PPO("MultiInputPolicy", env, n_steps=256, batch_size=512, seed=0, device="cpu")
model.learn(total_timesteps=steps)
model.save("ppo_derl_ft")
obs = env.reset()
forward = 0.0
for _ in range(1000):  # one episode of the trained policy in copy 0
    action, _ = model.predict(obs, deterministic=True)
    obs, reward, done, info = env.step(action)
    forward += info[0]["forward"]
    if done[0]:
        break
print(f"trained {steps:,} steps: an episode walked {forward / 50:.2f} m forward")
