"""What a paper-scale evolution costs: the wall clock of 4,000 bodies x 5M steps per world on one
64-core host, estimated from trainings measured here; prints JSON.

Per world (FT, VT, MVT) and reference body (6 and 10 limbs): a short training from scratch as an
evolution's trainer runs it (the environment of `derl.lifetime.learn`, PPO with the paper's
settings, one core), its env steps per CPU-second of the training process (on a shared machine
the wall clock also counts other processes' turns on the core). The world's rate per core is
that of its two bodies in equal numbers (the harmonic mean: each trains the same steps). Then
K = 2 trainings side by side, one per core (the world's two bodies at once), against each alone:
the share of its single-training speed each keeps (what the cores' shared caches and memory
cost). The estimate is 4,000 x 5M steps / (64 cores x rate per core x share), at the share
measured for K = 2 and at 0.80, the lowest share measured for 16 trainings on a 16-core host
(FT-6; VT-10 kept 0.95 at 8): the assumption for 64 until a 64-core host measures it. The rates
are those of a training's first iterations, when episodes are short; the coordinator and the bus
cost a few percent at 15 trainers (measured), not counted here.
Run: python bench/paper_scale.py [--iterations 10] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import multiprocessing.pool
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from bodies import reference_body

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.lifetime import ppo_config
from derl.rl import train

WORLDS = ("ft", "vt", "mvt")
LIMBS = (6, 10)
BODIES = 4000
STEPS = 5_000_000
CORES = 64
SHARE_AT_16 = 0.80


def rate(job: tuple[str, int, int]) -> float:
    """Env steps per CPU-second of a training of ``iterations`` PPO iterations of one body in
    one world (the environment built as `derl.lifetime.learn` builds it, then timed)."""
    world, limbs, iterations = job
    config = ppo_config(world, iterations * 4096, seed=0)
    env = UnimalEnv(reference_body(limbs), make_task(world), EnvConfig(num_envs=config.num_envs))
    start = time.process_time()
    result = train(env, config)
    return result.env_steps / (time.process_time() - start)


def hours(rate_per_core: float, share: float) -> float:
    """Wall-clock hours of `BODIES` trainings of `STEPS` on `CORES` cores."""
    return BODIES * STEPS / (CORES * rate_per_core * share) / 3600


def bench_world(
    world: str, iterations: int, repeats: int, pool: multiprocessing.pool.Pool
) -> dict[str, object]:
    jobs = [(world, limbs, iterations) for limbs in LIMBS]
    alone: dict[int, list[float]] = {limbs: [] for limbs in LIMBS}
    side: dict[int, list[float]] = {limbs: [] for limbs in LIMBS}
    for _ in range(repeats):
        for job in jobs:
            alone[job[1]].append(rate(job))
        for job, measured in zip(jobs, pool.map(rate, jobs), strict=True):
            side[job[1]].append(measured)
    rates = {limbs: statistics.median(alone[limbs]) for limbs in LIMBS}
    per_core = len(LIMBS) / sum(1.0 / r for r in rates.values())
    shares = [
        statistics.median(s / a for s, a in zip(side[n], alone[n], strict=True)) for n in LIMBS
    ]
    share = statistics.mean(shares)
    return {
        "world": world,
        "steps_per_s": {str(limbs): round(r) for limbs, r in rates.items()},
        "rate_per_core": round(per_core),
        "k2_share_kept": {str(limbs): round(s, 3) for limbs, s in zip(LIMBS, shares, strict=True)},
        "hours_at_k2_share": round(hours(per_core, share), 1),
        f"hours_at_{SHARE_AT_16}_share": round(hours(per_core, SHARE_AT_16), 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=10, help="PPO iterations of 4096 steps")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with multiprocessing.get_context("spawn").Pool(len(LIMBS)) as pool:
        worlds = [bench_world(w, args.iterations, args.repeats, pool) for w in WORLDS]
    total = {
        key: round(sum(w[key] for w in worlds), 1)
        for key in ("hours_at_k2_share", f"hours_at_{SHARE_AT_16}_share")
    }
    out = {
        "bodies": BODIES,
        "steps_per_body": STEPS,
        "cores": CORES,
        "worlds": worlds,
        "three_worlds_hours": total,
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
