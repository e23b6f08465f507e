"""Train a derl body with Stable-Baselines3's PPO: derl's worlds are gymnasium environments.

    pip install 'derl[bench]'                                  # Stable-Baselines3
    MUJOCO_GL=egl python examples/stable_baselines3_ft.py bodies/unimal_0000.json [STEPS]

`import derl` registers every task as ``derl/<Task>-v0``; each environment is one copy of the
simulation derl trains in, its observations a dict of float32 arrays (``proprioception``, and by
task ``heightmap``, ``object``, ``goal``): Stable-Baselines3's ``MultiInputPolicy`` takes them.
The reward is the task's, and ``info["forward"]`` the fitness term of each step (FT and VT: 50
per metre forward in an episode). bench/peers.py runs this with the paper's settings beside
derl's own PPO.
"""

import sys

import gymnasium
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env

import derl  # noqa: F401 (registers derl/FT-v0 and the other tasks)

genome, steps = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 100_000
env = make_vec_env(lambda: gymnasium.make("derl/FT-v0", genome=genome), n_envs=8)
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
