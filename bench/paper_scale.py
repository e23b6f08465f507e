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
(FT-6; VT-10 kept 0.95 at 8): the assumption for 64 until a 64-core host measures it. Beside
it, the floor that no work outside the simulator can lower: the hours if a training cost only
its MuJoCo time (its ``physics_share`` of the wall time, by the environment's own clock).
These rates are those of a training's first iterations, when episodes are short. With
``--lifetime`` each world's two bodies are trained side by side for a whole lifetime (5M steps
each, so the rates hold the share two trainings keep), and the estimate is made from the rates
over the lifetime, which hold what later iterations cost (longer episodes, bodies on the
obstacles); ``lifetime_over_early`` compares them with the first ``--iterations``. The
coordinator and the bus cost a few percent at 15 trainers (measured), not counted here.
Run: python bench/paper_scale.py [--iterations 10] [--repeats 3] [--lifetime] [--worlds ft vt]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import multiprocessing.pool
import statistics
import time
from collections.abc import Iterable

from bodies import reference_body

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.lifetime import ppo_config
from derl.rl import Progress, TrainResult, train

WORLDS = ("ft", "vt", "mvt")
LIMBS = (6, 10)
BODIES = 4000
STEPS = 5_000_000
CORES = 64
SHARE_AT_16 = 0.80


def training(
    world: str, limbs: int, steps: int, early: int = 0
) -> tuple[TrainResult, float, float | None]:
    """A training of ``steps`` env steps of one body in one world, the environment built as
    `derl.lifetime.learn` builds it: its result, its env steps per CPU-second, and those over
    its first ``early`` iterations (None for 0)."""
    config = ppo_config(world, steps, seed=0)
    env = UnimalEnv(reference_body(limbs), make_task(world), EnvConfig(num_envs=config.num_envs))
    first: list[float] = []

    def at(progress: Progress) -> None:
        if progress.iteration == early:
            first.append(progress.env_steps / (time.process_time() - start))

    start = time.process_time()
    result = train(env, config, at)
    return result, result.env_steps / (time.process_time() - start), (first or [None])[0]


def physics_share(result: TrainResult) -> float:
    """The share of a training's wall time spent in MuJoCo (its steps and the forward passes
    of resets)."""
    assert result.time_split.physics_s is not None  # `UnimalEnv` counts it
    return result.time_split.physics_s / result.wall_time_s


def rate(job: tuple[str, int, int]) -> tuple[float, float]:
    """Env steps per CPU-second of a training of ``iterations`` PPO iterations of one body in
    one world, and its `physics_share`."""
    world, limbs, iterations = job
    result, steps_per_s, _ = training(world, limbs, iterations * 4096)
    return steps_per_s, physics_share(result)


def lifetime(job: tuple[str, int, int]) -> dict[str, float]:
    """A whole lifetime (`STEPS`) of one body in one world: its env steps per CPU-second over
    the first ``early`` iterations and over all of it, the shares of its wall time (MuJoCo, the
    rest of the environment, the update, inference, the rest) and of flat heightmap rows (-1:
    no heightmap)."""
    world, limbs, early = job
    result, steps_per_s, first = training(world, limbs, STEPS, early)
    assert first is not None, "early must be within the lifetime's iterations"
    split, wall, physics = result.time_split, result.wall_time_s, physics_share(result)
    return {
        "early": first,
        "lifetime": steps_per_s,
        "physics_share": physics,
        "env_beyond_physics_share": split.env_s / wall - physics,
        "update_share": split.update_s / wall,
        "inference_share": split.inference_s / wall,
        "other_share": split.other_s / wall,
        "flat_rows": -1.0 if result.flat_rows is None else result.flat_rows,
        "fitness": result.fitness,
    }


def hours(rate_per_core: float, share: float) -> float:
    """Wall-clock hours of `BODIES` trainings of `STEPS` on `CORES` cores."""
    return BODIES * STEPS / (CORES * rate_per_core * share) / 3600


def bench_world(
    world: str, iterations: int, repeats: int, pool: multiprocessing.pool.Pool
) -> dict[str, object]:
    jobs = [(world, limbs, iterations) for limbs in LIMBS]
    alone: dict[int, list[float]] = {limbs: [] for limbs in LIMBS}
    side: dict[int, list[float]] = {limbs: [] for limbs in LIMBS}
    in_physics: dict[int, list[float]] = {limbs: [] for limbs in LIMBS}
    for _ in range(repeats):
        for job in jobs:
            measured, physics = rate(job)
            alone[job[1]].append(measured)
            in_physics[job[1]].append(physics)
        for job, (measured, _) in zip(jobs, pool.map(rate, jobs), strict=True):
            side[job[1]].append(measured)
    rates = {limbs: statistics.median(alone[limbs]) for limbs in LIMBS}
    physics = {limbs: statistics.median(in_physics[limbs]) for limbs in LIMBS}
    per_core = harmonic(rates.values())
    physics_per_core = harmonic(rates[n] / physics[n] for n in LIMBS)
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
        "physics_share": {str(limbs): round(p, 3) for limbs, p in physics.items()},
        "hours_physics_only_at_k2_share": round(hours(physics_per_core, share), 1),
    }


def bench_lifetime(world: str, early: int, pool: multiprocessing.pool.Pool) -> dict[str, object]:
    """The world's two bodies trained side by side for a whole lifetime each (so their rates
    hold the share two trainings keep), and the paper-scale hours at those rates."""
    runs = dict(zip(LIMBS, pool.map(lifetime, [(world, n, early) for n in LIMBS]), strict=True))
    rates = [runs[n]["lifetime"] for n in LIMBS]
    return {
        "world": world,
        "bodies": {str(n): {k: round(v, 3) for k, v in r.items()} for n, r in runs.items()},
        "lifetime_over_early": round(
            harmonic(rates) / harmonic(runs[n]["early"] for n in LIMBS), 3
        ),
        "hours_at_lifetime_rates": round(hours(harmonic(rates), 1.0), 1),
        "hours_physics_only": round(
            hours(harmonic(runs[n]["lifetime"] / runs[n]["physics_share"] for n in LIMBS), 1.0), 1
        ),
    }


def harmonic(rates: Iterable[float]) -> float:
    """The rate of trainings of equal steps, one at each of `rates`."""
    inverse = [1.0 / r for r in rates]
    return len(inverse) / sum(inverse)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=10, help="PPO iterations of 4096 steps")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--lifetime",
        action="store_true",
        help="train each body for a whole lifetime instead (two side by side; about an hour)",
    )
    parser.add_argument("--worlds", nargs="+", choices=WORLDS, default=WORLDS)
    args = parser.parse_args()
    with multiprocessing.get_context("spawn").Pool(len(LIMBS)) as pool:
        if args.lifetime:
            worlds = [bench_lifetime(w, args.iterations, pool) for w in args.worlds]
        else:
            worlds = [bench_world(w, args.iterations, args.repeats, pool) for w in args.worlds]
    total = {
        key: round(sum(w[key] for w in worlds), 1) for key in worlds[0] if key.startswith("hours")
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
