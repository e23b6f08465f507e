"""Does MuJoCo's sleeping change MVT's fitness? The same bodies trained with and without it (same
seeds); prints JSON.

MVT's box sleeps once at rest (`EnvConfig.sleep`), an approximation the released code did not
make. Per seed: a training of ``--steps`` of a reference body with sleeping and one without,
everything else equal (both in two processes, one per core). Reported per seed and arm: the
fitness (the released code's: reach + push over the last iterations), env steps per CPU-second,
and the share of episodes in which the agent moved the box (a push term of at least 1, i.e. 1 cm
towards or away from its goal after reaching it). The comparison: the mean of the paired
differences (with - without) against the seed-to-seed standard deviation of each arm. With
``--near`` the box is 1-2 m ahead (its goal as far again beyond it) instead of 15-24 m, so that
short trainings reach and push it, where sleeping could matter (3-5 m ahead, 200k-step
trainings of the 6-limb body never moved it).
Run: python bench/sleep.py [--steps 200000] [--seeds 4] [--limbs 6] [--near]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bodies import reference_body

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.envs.worlds import BoxPlacement
from derl.lifetime import ppo_config
from derl.rl import train

NEAR = BoxPlacement(ahead=(1, 2))


def training(job: tuple[int, bool, int, int, bool]) -> dict[str, float]:
    """One MVT training: fitness, env steps per CPU-second, share of episodes that moved the box."""
    seed, sleep, limbs, steps, near = job
    task = make_task("mvt", placement=NEAR) if near else make_task("mvt")
    config = ppo_config("mvt", steps, seed)
    env = UnimalEnv(reference_body(limbs), task, EnvConfig(num_envs=config.num_envs, sleep=sleep))
    start = time.process_time()
    result = train(env, config)
    cpu = time.process_time() - start
    push = result.episodes.components["push"]
    return {
        "fitness": result.fitness,
        "steps_per_cpu_s": result.env_steps / cpu,
        "moved_box_share": float(np.mean(np.abs(push) >= 1.0)) if len(push) else 0.0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--limbs", type=int, choices=(6, 10), default=6)
    parser.add_argument("--near", action="store_true", help="the box 1-2 m ahead")
    args = parser.parse_args()
    jobs = [
        (seed, sleep, args.limbs, args.steps, args.near)
        for seed in range(args.seeds)
        for sleep in (True, False)
    ]
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        runs = pool.map(training, jobs)
    arms = {
        name: [run for job, run in zip(jobs, runs, strict=True) if job[1] == sleep]
        for name, sleep in (("sleep", True), ("awake", False))
    }
    fitness = {name: [r["fitness"] for r in arm] for name, arm in arms.items()}
    paired = [a - b for a, b in zip(fitness["sleep"], fitness["awake"], strict=True)]
    out = {
        "limbs": args.limbs,
        "steps": args.steps,
        "box_ahead_m": list(NEAR.ahead) if args.near else [15, 24],
        **{
            name: {
                "fitness": [round(f, 2) for f in fitness[name]],
                "fitness_mean": round(statistics.mean(fitness[name]), 2),
                "fitness_seed_sd": round(statistics.stdev(fitness[name]), 2),
                "steps_per_cpu_s_median": round(
                    statistics.median(r["steps_per_cpu_s"] for r in arm)
                ),
                "moved_box_share": [round(r["moved_box_share"], 3) for r in arm],
            }
            for name, arm in arms.items()
        },
        "paired_difference_mean": round(statistics.mean(paired), 2),
        "paired_differences": [round(d, 2) for d in paired],
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
