"""Benchmark of lifetime learning (sample + learn, PPO with the paper's settings); prints JSON.

For FT and VT with a 6- and a 10-limb body, on one core: end-to-end env steps/s of a short
training, the raw physics rate of the same body measured in the same run (the same
`mujoco.batch.Batch` stepping alone: the ceiling), their ratio, and where the wall time went, as
shares and in microseconds per env step: physics (MuJoCo's time inside the training, which the
environment counts: its steps and the forward passes of reset copies), the environment's own work
(observations, rewards, resets), inference, the PPO update and the rest; beside them the physics at
the raw rate and the update's arithmetic at the matrix rate, the bound's two terms. Also the
**bound**: the end-to-end rate if everything but the physics and the update's arithmetic (its FLOPs
at this core's best single-thread matrix rate, measured in the same run) were free, and the
**efficiency** = end-to-end rate / bound. The bound's physics is MuJoCo's time for the median
training's very steps replayed alone (`replayed_physics_s`: the same body, seed and actions give
the same states; no network in between), so that states that cost more or less than the raw rate's
(random actions from a standing start) move the bound, not the efficiency; the bound from the raw
rate is printed beside it (`*_at_raw_physics`). On VT the update skips the first-layer products of
heightmap rows that are all zero (flat ground; `derl.rl.fused.SPARSE`): the bench prints their
share and, beside the bound of the full arithmetic, the bound and efficiency of the arithmetic
actually done (`*_rows_done`). Then K trainings side by side in K processes (K = every core of the
machine) against one alone: the share of single-training speed each keeps.
Run: python bench/train.py [--iterations 20] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import time

import mujoco
import numpy as np
import torch
from bodies import reference_body

from derl.envs import UnimalEnv, make_env
from derl.lifetime import ppo_config
from derl.rl import ActorCritic, PPOConfig, train
from derl.rl.fused import SPARSE


def raw_physics_rate(world: str, limbs: int, steps: int = 200) -> float:
    env = make_env(reference_body(limbs), world, num_envs=32, seed=0)
    env.reset(0)
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, 32, env.action_dim))
    start = time.perf_counter()
    for t in range(steps):
        env.ctrl[:] = actions[t]
        env.batch.step(nstep=4, stage=mujoco.mjtStage.mjSTAGE_VEL)
    return steps * 32 / (time.perf_counter() - start)


def matrix_flops_per_s(repeats: int = 5) -> float:
    """This core's best float32 matrix rate (one thread): the update's own shapes, a minibatch of
    512 rows through a 64-wide layer, forward and backward products."""
    torch.set_num_threads(1)
    rate = 0.0
    for rows, inner, cols in ((512, 1410, 64), (512, 64, 64), (64, 512, 64)):
        a, b, out = torch.randn(rows, inner), torch.randn(inner, cols), torch.empty(rows, cols)
        calls = max(1, int(2e8 // (2 * rows * inner * cols)))
        for _ in range(repeats):
            start = time.perf_counter()
            for _ in range(calls):
                torch.mm(a, b, out=out)
            rate = max(rate, calls * 2 * rows * inner * cols / (time.perf_counter() - start))
    return rate


def update_flops_per_step(world: str, limbs: int, flat_rows: float = 0.0) -> float:
    """The PPO update's multiply-add FLOPs per env step: every sample goes through the actor and
    the critic `epochs` times, forward (2 FLOPs per weight) and backward (2 per weight for the
    weight's gradient, 2 more for the layer input's gradient, which the first layers skip).
    `flat_rows`: the share of samples whose heightmap is all zero, for which the heightmap's
    first layers (forward and weight gradient: 4 FLOPs per weight) are skipped."""
    env = make_env(reference_body(limbs), world, num_envs=1, seed=0)
    net = ActorCritic(env.obs_spaces, env.action_dim)
    firsts = {
        key: branch[0].weight.numel()
        for encoder in (net.actor, net.critic)
        for key, branch in encoder.branches.items()
    }
    first = sum(firsts.values()) * 2  # both encoders have the same branches
    weights = sum(m.weight.numel() for m in net.modules() if isinstance(m, torch.nn.Linear))
    skipped = flat_rows * 4.0 * 2 * firsts.get(SPARSE, 0)
    return PPOConfig().epochs * (6.0 * weights - 2.0 * first - skipped)


class Recorded:
    """An environment that keeps a copy of every action it is given, so that its training's
    steps can be replayed (`replayed_physics_s`); everything else is the environment's own."""

    def __init__(self, env: UnimalEnv) -> None:
        self.env = env
        self.actions: list[np.ndarray] = []

    def __getattr__(self, name: str) -> object:  # num_envs, obs_spaces, action_dim, physics_s
        return getattr(self.env, name)

    def reset(self, seed: int) -> dict[str, np.ndarray]:
        return self.env.reset(seed)

    def step(self, actions: np.ndarray) -> object:
        self.actions.append(actions.copy())
        return self.env.step(actions)


def _training_env(world: str, limbs: int, config: PPOConfig) -> UnimalEnv:
    """The environment a training with `config` runs in (as `derl.lifetime.learn` makes it)."""
    return make_env(reference_body(limbs), world, config.num_envs, config.seed)


def training(world: str, limbs: int, iterations: int) -> dict[str, object]:
    """A short training (as `derl.lifetime.learn` runs it), with its actions and final state."""
    config = ppo_config(world, iterations * 4096, seed=0)
    env = Recorded(_training_env(world, limbs, config))
    result = train(env, config)
    flat = {} if result.flat_rows is None else {"flat_rows": result.flat_rows}
    return {
        "steps_per_s": result.steps_per_second,
        **{k: v for k, v in vars(result.time_split).items() if v is not None},
        **flat,
        "config": config,
        "actions": env.actions,
        "final_qpos": env.env.qpos.copy(),
    }


def replayed_physics_s(world: str, limbs: int, run: dict[str, object]) -> float:
    """MuJoCo's time for the very steps of training `run`, replayed alone: the same body, seed
    and actions give the same states, resets included (checked on the final state), without
    the network's work in between. This is the bound's physics term: the raw rate steps other
    states (random actions from a standing start), which cost less or more than a training's."""
    config = run["config"]
    env = _training_env(world, limbs, config)
    env.reset(config.seed)
    before = env.physics_s
    for actions in run["actions"]:
        env.step(actions)
    if not np.array_equal(env.qpos, run["final_qpos"]):
        raise RuntimeError(f"the replay of {world}-{limbs} did not end in its training's state")
    return env.physics_s - before


def bench_config(
    world: str, limbs: int, iterations: int, repeats: int, flops: float
) -> dict[str, object]:
    raw, runs = [], []
    for _ in range(repeats):
        raw.append(raw_physics_rate(world, limbs))
        runs.append(training(world, limbs, iterations))
    raw_rate = statistics.median(raw)
    best = sorted(runs, key=lambda r: r["steps_per_s"])[len(runs) // 2]  # the median run
    steps = iterations * 4096
    physics = replayed_physics_s(world, limbs, best) / steps  # the bound's physics, s per step
    update_flops = update_flops_per_step(world, limbs)
    bound = 1.0 / (physics + update_flops / flops)
    at_raw = 1.0 / (1.0 / raw_rate + update_flops / flops)
    rows_done = {}
    if "flat_rows" in best:
        done_flops = update_flops_per_step(world, limbs, best["flat_rows"])
        done_bound = 1.0 / (physics + done_flops / flops)
        rows_done = {
            "flat_heightmap_rows": round(best["flat_rows"], 3),
            "update_mflop_per_step_rows_done": round(done_flops / 1e6, 2),
            "bound_steps_per_s_rows_done": round(done_bound),
            "efficiency_rows_done": round(best["steps_per_s"] / done_bound, 3),
        }
    wall = sum(best[k] for k in ("env_s", "inference_s", "update_s", "other_s"))
    parts = {  # seconds of the median run, by where they went
        "physics": best["physics_s"],
        "observations_rewards_resets": best["env_s"] - best["physics_s"],
        "inference": best["inference_s"],
        "update": best["update_s"],
        "other": best["other_s"],
    }
    return {
        "world": world,
        "limbs": limbs,
        "end_to_end_steps_per_s": round(best["steps_per_s"]),
        "raw_physics_steps_per_s": round(raw_rate),
        "ratio": round(best["steps_per_s"] / raw_rate, 3),
        "update_mflop_per_step": round(update_flops / 1e6, 2),
        "bound_steps_per_s": round(bound),
        "efficiency": round(best["steps_per_s"] / bound, 3),
        **rows_done,
        # the bound as it was computed before the replay, from the raw rate
        "bound_steps_per_s_at_raw_physics": round(at_raw),
        "efficiency_at_raw_physics": round(best["steps_per_s"] / at_raw, 3),
        "share": {name: round(seconds / wall, 3) for name, seconds in parts.items()},
        "us_per_env_step": {
            **{name: round(seconds / steps * 1e6, 2) for name, seconds in parts.items()},
            "physics_replayed": round(physics * 1e6, 2),
            "physics_at_raw_rate": round(1e6 / raw_rate, 2),
            "update_arithmetic_at_matrix_rate": round(update_flops / flops * 1e6, 2),
        },
    }


def _worker(args: tuple[str, int, int]) -> float:
    return training(*args)["steps_per_s"]


def bench_parallel(iterations: int) -> dict[str, object]:
    """K trainings (FT, 6 limbs) at once on K cores against one alone."""
    cores = len(os.sched_getaffinity(0))
    job = ("ft", 6, iterations)
    alone = _worker(job)
    with multiprocessing.get_context("spawn").Pool(cores) as pool:
        side_by_side = pool.map(_worker, [job] * cores)
    return {
        "trainings": cores,
        "alone_steps_per_s": round(alone),
        "side_by_side_steps_per_s": [round(s) for s in side_by_side],
        "kept_share_min": round(min(side_by_side) / alone, 3),
        "kept_share_median": round(statistics.median(side_by_side) / alone, 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=20, help="PPO iterations of 4096 steps")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    flops = matrix_flops_per_s()
    results = [
        bench_config(world, limbs, args.iterations, args.repeats, flops)
        for world in ("ft", "vt")
        for limbs in (6, 10)
    ]
    out = {
        "matrix_gflops_per_s": round(flops / 1e9, 1),
        "configs": results,
        "k_trainings_on_k_cores": bench_parallel(args.iterations),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
