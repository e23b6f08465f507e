"""Benchmark of lifetime learning (sample + learn, PPO with the paper's settings); prints JSON.

For FT and VT with a 6- and a 10-limb body, on one core: end-to-end env steps/s of a short
training, the raw physics rate of the same body measured in the same run (the same
`mujoco.batch.Batch` stepping alone: the ceiling), their ratio, and the share of wall time in
physics, observations/rewards/resets, inference and the PPO update. Then two trainings side by
side in two processes against one alone: the share of single-core speed each keeps.
Run: python bench/train.py [--iterations 20] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bodies import reference_body

from derl.envs import make_env
from derl.lifetime import learn, ppo_config


def raw_physics_rate(world: str, limbs: int, steps: int = 200) -> float:
    env = make_env(reference_body(limbs), world, num_envs=32, seed=0)
    env.reset(0)
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, 32, env.action_dim))
    start = time.perf_counter()
    for t in range(steps):
        env.ctrl[:] = actions[t]
        env.batch.step(nstep=4, stage=mujoco.mjtStage.mjSTAGE_VEL)
    return steps * 32 / (time.perf_counter() - start)


def training(world: str, limbs: int, iterations: int) -> dict[str, float]:
    config = ppo_config(world, iterations * 4096, seed=0)
    summary, _ = learn(reference_body(limbs), world, config)
    return {"steps_per_s": summary.steps_per_second, **summary.time_split}


def bench_config(world: str, limbs: int, iterations: int, repeats: int) -> dict[str, object]:
    raw, runs = [], []
    for _ in range(repeats):
        raw.append(raw_physics_rate(world, limbs))
        runs.append(training(world, limbs, iterations))
    raw_rate = statistics.median(raw)
    best = sorted(runs, key=lambda r: r["steps_per_s"])[len(runs) // 2]  # the median run
    wall = sum(best[k] for k in ("env_s", "inference_s", "update_s", "other_s"))
    physics = iterations * 4096 / raw_rate
    return {
        "world": world,
        "limbs": limbs,
        "end_to_end_steps_per_s": round(best["steps_per_s"]),
        "raw_physics_steps_per_s": round(raw_rate),
        "ratio": round(best["steps_per_s"] / raw_rate, 3),
        "share": {
            "physics": round(physics / wall, 3),
            "observations_rewards_resets": round((best["env_s"] - physics) / wall, 3),
            "inference": round(best["inference_s"] / wall, 3),
            "update": round(best["update_s"] / wall, 3),
            "other": round(best["other_s"] / wall, 3),
        },
    }


def _worker(args: tuple[str, int, int]) -> float:
    return training(*args)["steps_per_s"]


def bench_parallel(iterations: int) -> dict[str, float]:
    job = ("ft", 6, iterations)
    alone = _worker(job)
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        side_by_side = pool.map(_worker, [job, job])
    return {
        "alone_steps_per_s": round(alone),
        "side_by_side_steps_per_s": [round(s) for s in side_by_side],
        "kept_share": round(min(side_by_side) / alone, 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=20, help="PPO iterations of 4096 steps")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    results = [
        bench_config(world, limbs, args.iterations, args.repeats)
        for world in ("ft", "vt")
        for limbs in (6, 10)
    ]
    out = {"configs": results, "two_trainings_on_two_cores": bench_parallel(args.iterations)}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
