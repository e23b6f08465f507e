"""Does MuJoCo's sleeping change MVT's fitness? The same bodies trained with and without it (same
seeds); prints JSON.

MVT's box sleeps once at rest (`EnvConfig.sleep`), an approximation the released code did not
make. Per seed: a training of ``--steps`` of a body with sleeping and one without, everything
else equal (a pair). Reported per training: the fitness (the released code's: reach + push over
the last iterations), the reach and push terms (their mean episode sums over the episodes that
finished in the fitness window), env steps per CPU-second and per wall second, and the share of
episodes in which the agent moved the box (a push term of at least 1, i.e. 1 cm towards or away
from its goal after reaching it), over the whole training and over the window. The comparison:
the paired differences (asleep minus awake), their mean with a 95% t-interval (n - 1 degrees of
freedom: with 3 pairs its half-width is 4.3 standard errors, a wide interval), against the
seed-to-seed standard deviation of each arm.

Two set-ups:
- the default: the 6- or 10-limb reference body (``--limbs``), trained as `derl.rl.train` on an
  env built here (env seed 0), the box 15-24 m ahead, or with ``--near`` 1-2 m ahead (its goal as
  far again beyond it), so that short trainings reach and push it (3-5 m ahead, 200k-step
  trainings of the 6-limb body never moved it); two trainings at a time (one per core).
- ``--genome FILE``: that body (e.g. the shipped MVT agent, agents/mvt/genome.json) trained as
  evolution trains it, `derl.lifetime.learn(genome, "mvt", ppo_config("mvt", steps, seed))`, in
  the real MVT world (the box 15-24 m ahead), its env config's ``sleep`` switched; training
  seeds from ``--first-seed``. With ``--processes 1`` the trainings run one after another in
  this process (each prints a JSON line to stderr as it ends).

Run: python bench/sleep.py [--steps 200000] [--seeds 4] [--limbs 6] [--near]
     python bench/sleep.py --genome agents/mvt/genome.json --steps 1000000 --seeds 3 \
         --first-seed 1409 --processes 1
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import time
from pathlib import Path
from typing import NamedTuple
from unittest import mock

import numpy as np
from bodies import reference_body
from scipy import stats

from derl import lifetime
from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.envs.worlds import BoxPlacement
from derl.lifetime import ppo_config
from derl.rl import train
from derl.unimal import Genome

NEAR = BoxPlacement(ahead=(1, 2))
MOVED = 1.0
"""A push term (an episode's sum) of at least this moved the box (1 cm)."""


class Job(NamedTuple):
    seed: int
    sleep: bool
    steps: int
    limbs: int
    near: bool
    genome: str | None  # a genome's JSON text: trained by `derl.lifetime.learn`


def _moved(push: np.ndarray) -> float:
    return float(np.mean(np.abs(push) >= MOVED)) if len(push) else 0.0


def training(job: Job) -> dict[str, object]:
    """One MVT training: fitness, reach and push, env steps per CPU-second and per second, share
    of episodes that moved the box."""
    config = ppo_config("mvt", job.steps, job.seed)
    start = time.process_time()
    if job.genome is None:
        task = make_task("mvt", placement=NEAR) if job.near else make_task("mvt")
        env_config = EnvConfig(num_envs=config.num_envs, sleep=job.sleep)
        result = train(UnimalEnv(reference_body(job.limbs), task, env_config), config)
    else:
        made: list[EnvConfig] = []

        def env_config(**fields: object) -> EnvConfig:  # learn's EnvConfig, sleep switched
            made.append(EnvConfig(**{**fields, "sleep": job.sleep}))
            return made[-1]

        with mock.patch.object(lifetime, "EnvConfig", env_config):
            _, result = lifetime.learn(Genome.model_validate_json(job.genome), "mvt", config)
        assert [c.sleep for c in made] == [job.sleep], made
    cpu = time.process_time() - start
    log = result.episodes
    window = log.finish_step > result.env_steps - config.fitness_window_steps
    reach, push = log.components["reach"], log.components["push"]
    return {
        "seed": job.seed,
        "sleep": job.sleep,
        "fitness": round(result.fitness, 2),
        "fitness_source": result.fitness_source,
        "reach_window": round(float(reach[window].mean()), 2) if window.any() else None,
        "push_window": round(float(push[window].mean()), 2) if window.any() else None,
        "episodes": len(log),
        "window_episodes": int(window.sum()),
        "moved_box_share": round(_moved(push), 4),
        "moved_box_share_window": round(_moved(push[window]), 4),
        "steps_per_cpu_s": round(result.env_steps / cpu),
        "steps_per_s": round(result.steps_per_second),
        "physics_s": round(result.time_split.physics_s or 0.0, 1),
        "wall_s": round(result.wall_time_s, 1),
    }


def _logged(job: Job) -> dict[str, object]:
    run = training(job)
    print(json.dumps(run), file=sys.stderr, flush=True)
    return run


def t_interval(values: list[float], confidence: float = 0.95) -> list[float]:
    """The mean's two-sided t-interval (n - 1 degrees of freedom)."""
    half = stats.t.ppf((1 + confidence) / 2, len(values) - 1) * stats.sem(values)
    mean = statistics.mean(values)
    return [round(mean - half, 2), round(mean + half, 2)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200_000)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--first-seed", type=int, default=0, help="the first training seed")
    parser.add_argument("--limbs", type=int, choices=(6, 10), default=6)
    parser.add_argument("--near", action="store_true", help="the box 1-2 m ahead")
    parser.add_argument(
        "--genome", type=Path, help="train this body as evolution does (derl.lifetime.learn)"
    )
    parser.add_argument("--processes", type=int, choices=(1, 2), default=2)
    args = parser.parse_args()
    if args.genome and args.near:
        parser.error("--near places the box for the reference bodies only")
    if args.seeds < 2:
        parser.error("--seeds: at least 2 (a spread and an interval)")
    genome = args.genome.read_text() if args.genome else None
    jobs = [
        Job(seed, sleep, args.steps, args.limbs, args.near, genome)
        for seed in range(args.first_seed, args.first_seed + args.seeds)
        for sleep in (True, False)
    ]
    if args.processes == 1:
        runs = [_logged(job) for job in jobs]
    else:
        with multiprocessing.get_context("spawn").Pool(2) as pool:
            runs = pool.map(_logged, jobs)
    arms = {
        name: [run for job, run in zip(jobs, runs, strict=True) if job.sleep == sleep]
        for name, sleep in (("sleep", True), ("awake", False))
    }
    fitness = {name: [float(r["fitness"]) for r in arm] for name, arm in arms.items()}
    paired = [a - b for a, b in zip(fitness["sleep"], fitness["awake"], strict=True)]
    ratios = [
        a["steps_per_cpu_s"] / b["steps_per_cpu_s"]
        for a, b in zip(arms["sleep"], arms["awake"], strict=True)
    ]
    out = {
        "body": str(args.genome) if args.genome else f"reference, {args.limbs} limbs",
        "trained_by": "derl.lifetime.learn" if args.genome else "derl.rl.train (env seed 0)",
        "steps": args.steps,
        "seeds": [job.seed for job in jobs if job.sleep],
        "box_ahead_m": list(NEAR.ahead) if args.near else [15, 24],
        "processes": args.processes,
        **{
            name: {
                "fitness": fitness[name],
                "fitness_mean": round(statistics.mean(fitness[name]), 2),
                "fitness_seed_sd": round(statistics.stdev(fitness[name]), 2),
                "reach_window": [r["reach_window"] for r in arm],
                "push_window": [r["push_window"] for r in arm],
                "moved_box_share": [r["moved_box_share"] for r in arm],
                "moved_box_share_window": [r["moved_box_share_window"] for r in arm],
                "steps_per_cpu_s": [r["steps_per_cpu_s"] for r in arm],
                "steps_per_cpu_s_median": round(
                    statistics.median(r["steps_per_cpu_s"] for r in arm)
                ),
                "steps_per_s": [r["steps_per_s"] for r in arm],
            }
            for name, arm in arms.items()
        },
        "paired_differences": [round(d, 2) for d in paired],
        "paired_difference_mean": round(statistics.mean(paired), 2),
        "paired_difference_sd": round(statistics.stdev(paired), 2),
        "paired_difference_ci95": t_interval(paired),
        "ci_note": f"t-interval on {len(paired)} pairs ({len(paired) - 1} degrees of freedom): "
        f"half-width {stats.t.ppf(0.975, len(paired) - 1):.2f} standard errors, wide",
        "speed_ratio_cpu": [round(r, 2) for r in ratios],
        "speed_ratio_cpu_mean": round(statistics.mean(ratios), 2),
        "runs": runs,
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
