"""derl's PPO against Stable-Baselines3's on the same body, world, budget and seed; prints JSON.

Both train the 6-limb reference body (`bench/bodies.py`) on FT for the same env steps with the
paper's settings: 32 copies x 128 steps per rollout, 4 epochs of minibatches of 512, GAE 0.99 /
0.95, clip 0.2, entropy 0.01, value 0.5, grad norm 0.5, Adam 3e-4 decayed linearly, separate
[64, 64] tanh actor and critic, observations and rewards normalised and clipped at 10. derl
trains its own batched environment (`derl.lifetime.learn`); Stable-Baselines3 trains 32 of
derl's gymnasium environments (`derl/FT-v0`: one copy of the same simulation each) in a
`DummyVecEnv` under `VecNormalize`. Both fitnesses are derl's definition (`derl.lifetime`): per
iteration the mean forward-progress sum of the last 10 finished episodes, averaged over the last
iterations of the released code's share of the training. Printed: env steps/s, wall time and
fitness of each, and the ratios (the goal: derl at least 10x the throughput, fitness no worse).
Needs the bench extra: pip install 'derl[bench]'.
Run: python bench/peers.py [--steps 200000] [--seed 1409]
"""

from __future__ import annotations

import argparse
import json
import time
from collections import deque

import numpy as np
import torch
from bodies import reference_body

from derl.lifetime import fitness_window, learn, ppo_config
from derl.unimal import Genome

LIMBS, WORLD = 6, "ft"


def derl_ppo(genome: Genome, steps: int, seed: int) -> dict[str, float]:
    summary, _ = learn(genome, WORLD, ppo_config(WORLD, steps, seed))
    return {
        "env_steps": summary.env_steps,
        "wall_s": summary.wall_time_s,
        "steps_per_s": summary.steps_per_second,
        "fitness": summary.fitness,
    }


def sb3_ppo(genome: Genome, steps: int, seed: int) -> dict[str, float]:
    """Stable-Baselines3's PPO with the paper's settings on 32 gymnasium copies of the body."""
    import gymnasium
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    config = ppo_config(WORLD, steps, seed)
    n = config.num_envs

    def make() -> gymnasium.Env:
        return gymnasium.make(f"derl/{WORLD.upper()}-v0", genome=genome)

    env = VecNormalize(
        DummyVecEnv([make] * n),
        gamma=config.gamma,
        clip_obs=config.obs_clip,
        clip_reward=config.reward_clip,
    )
    env.seed(seed)

    class Fitness(BaseCallback):
        """derl's fitness from the episodes' forward-progress sums (`info["forward"]`)."""

        def __init__(self) -> None:
            super().__init__()
            self.running = np.zeros(n)
            self.recent: deque[float] = deque(maxlen=config.recent_episodes)
            self.curve: list[tuple[int, float]] = []

        def _on_step(self) -> bool:
            self.running += [info["forward"] for info in self.locals["infos"]]
            for k in np.flatnonzero(self.locals["dones"]):
                self.recent.append(float(self.running[k]))
                self.running[k] = 0.0
            return True

        def _on_rollout_end(self) -> None:
            if len(self.recent) >= 2:
                self.curve.append((self.num_timesteps, float(np.mean(self.recent))))

    model = PPO(
        "MultiInputPolicy",
        env,
        learning_rate=lambda remaining: config.lr * remaining,
        n_steps=config.rollout_steps,
        batch_size=config.minibatch_size,
        n_epochs=config.epochs,
        gamma=config.gamma,
        gae_lambda=config.gae_lambda,
        clip_range=config.clip,
        clip_range_vf=config.value_clip,
        ent_coef=config.entropy_coef,
        vf_coef=config.value_coef,
        max_grad_norm=config.max_grad_norm,
        policy_kwargs={
            "net_arch": {"pi": [64, 64], "vf": [64, 64]},
            "activation_fn": torch.nn.Tanh,
            "optimizer_kwargs": {"eps": config.adam_eps},
        },
        seed=seed,
        device="cpu",
    )
    fitness = Fitness()
    start = time.perf_counter()
    model.learn(total_timesteps=config.iterations * config.batch_size, callback=fitness)
    wall = time.perf_counter() - start
    env.close()
    done = model.num_timesteps
    window = fitness_window(config.iterations * config.batch_size, config.batch_size)
    values = [value for at, value in fitness.curve if at > done - window]
    return {
        "env_steps": done,
        "wall_s": wall,
        "steps_per_s": done / wall,
        "fitness": float(np.mean(values)) if values else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--seed", type=int, default=1409)
    args = parser.parse_args()
    torch.set_num_threads(1)  # one core each, as a derl trainer
    genome = reference_body(LIMBS)
    derl, sb3 = derl_ppo(genome, args.steps, args.seed), sb3_ppo(genome, args.steps, args.seed)
    print(
        json.dumps(
            {
                "body": f"reference {LIMBS}-limb",
                "world": WORLD,
                "steps": args.steps,
                "seed": args.seed,
                "derl": derl,
                "stable_baselines3": sb3,
                "throughput_ratio": derl["steps_per_s"] / sb3["steps_per_s"],
                "fitness_difference": derl["fitness"] - sb3["fitness"],
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
