"""Before/after trainings for a change of the learning or the worlds: the reference bodies trained
with the paper's PPO; prints JSON.

Run it on the commit before a change and on the commit after it (the same bodies, seeds and
budget; a training is deterministic on one machine) and compare. Per training: the fitness (the
run's definition, `derl.lifetime.ppo_config`) and, beside it, the mean of the learning curve's
last 100 values (the released code's window at any budget), the curve's last value, the episodes,
their mean length and the share that ended before the time limit (falls, the arena's edge), the
env steps/s, and where the trainer counts them the updates stopped early by the approximate KL
(`kl_stops`). Output: JSON lines, one per training as it finishes (a long run on a busy machine
keeps what it has measured), then one with the medians over the seeds per body and world.
Run: python bench/fidelity.py [--steps 1000000] [--seeds 1409] [--bodies ft:6 ft:10 vt:6]
[--jobs 1]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics

import numpy as np
from bodies import reference_body

from derl.envs import EnvConfig
from derl.lifetime import learn, ppo_config

RELEASED_WINDOW = 100
"""The released code's fitness window in iterations, whatever the budget."""


def training(job: tuple[str, int, int, int]) -> dict[str, object]:
    world, limbs, seed, steps = job
    summary, result = learn(reference_body(limbs), world, ppo_config(world, steps, seed))
    log = result.episodes
    returns = summary.curve_returns
    kl_stops = getattr(result, "kl_stops", None)  # counted by the trainer from 2026-12-04
    return {
        "world": world,
        "limbs": limbs,
        "seed": seed,
        "steps": summary.env_steps,
        "fitness": round(summary.fitness, 2),
        "fitness_source": summary.fitness_source,
        "fitness_last_100_iterations": round(float(np.mean(returns[-RELEASED_WINDOW:])), 2)
        if returns
        else None,
        "curve_last": round(returns[-1], 2) if returns else None,
        "episodes": len(log),
        "mean_episode_length": round(float(log.length.mean()), 1) if len(log) else None,
        "ended_early_share": round(float(np.mean(log.length < EnvConfig().episode_steps)), 3)
        if len(log)
        else None,
        "steps_per_s": round(summary.steps_per_second),
        **({} if kl_stops is None else {"kl_stops": kl_stops}),
    }


def medians(runs: list[dict[str, object]]) -> list[dict[str, object]]:
    groups: dict[tuple[str, int], list[dict[str, object]]] = {}
    for run in runs:
        groups.setdefault((run["world"], run["limbs"]), []).append(run)
    keys = ("fitness", "fitness_last_100_iterations", "mean_episode_length", "steps_per_s")
    return [
        {
            "world": world,
            "limbs": limbs,
            "seeds": len(group),
            **{
                key: statistics.median(values)
                for key in keys
                if (values := [r[key] for r in group if r[key] is not None])
            },
        }
        for (world, limbs), group in groups.items()
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1_000_000, help="env steps per training")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1409], help="training seeds")
    parser.add_argument(
        "--bodies", nargs="+", default=["ft:6", "ft:10", "vt:6"], help="WORLD:LIMBS"
    )
    parser.add_argument("--jobs", type=int, default=1, help="trainings at once (processes)")
    args = parser.parse_args()
    jobs = []
    for body in args.bodies:
        world, limbs = body.split(":")
        jobs += [(world, int(limbs), seed, args.steps) for seed in args.seeds]
    runs = []
    with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
        for run in pool.imap_unordered(training, jobs):
            print(json.dumps(run), flush=True)
            runs.append(run)
    print(json.dumps({"medians": medians(runs)}), flush=True)


if __name__ == "__main__":
    main()
