"""What inheriting the parent's weights (`inherit: parent`) does to an evolution, against training
every child from scratch (`inherit: none`, the paper's), on the same seed; prints JSON.

Both runs are the demo profile at the size given (by default smaller than demo: see
docs/extending.md, "Inheritance"), each evolved in its own process with one trainer training the
children in child order, which gives the births any number of trainers gives (the `in_flight`
window). The initial bodies are the same and train alike in both runs: they are trained once,
two processes sharing them, and both runs start from their results (their time is in each run's
`wall_s`); from the first tournament on the runs part. Progress goes to stderr. Per run: every
birth's fitness in child order (`fitness`), its children's mean, the best, the repeats born
untrained and the wall time. `paired`: the difference parent - none of the fitness of the child
of each tournament number (the same iteration of the same seed), its mean and a 95 % bootstrap
interval of that mean (10,000 resamples of the tournaments), and the same for the last half of
each seed's tournaments.
With several seeds (`--seeds 0 1`), each seed's runs and differences, the intervals of all the
differences pooled (which treat the children of a run as independent: optimistic), and
`over_seeds`: a t interval of the seeds' mean differences (the seed the unit). The defaults are
the size docs/extending.md reports.
Run: python bench/inherit.py [--total 24] [--population 6] [--tournament 3] [--in-flight 3]
[--steps 32768] [--seeds 0 1 2 3]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from typing import cast

import numpy as np
from scipy import stats

from derl.evolution import Evolution, EvolutionConfig, load_profile
from derl.lifetime import learn
from derl.unimal import Genome, MutationFailed

RESAMPLES = 10_000
INHERIT = ("none", "parent")


Trained = tuple[float, bytes, float]
"""A training's fitness, checkpoint and wall seconds."""


def train(config: EvolutionConfig, genome: Genome, parent: tuple[Genome, bytes] | None) -> Trained:
    start = time.perf_counter()
    summary, result = learn(genome, config.world, config.training_ppo(), parent=parent)
    return summary.fitness, result.checkpoint.to_bytes(), time.perf_counter() - start


def train_initial(config: EvolutionConfig, name: str) -> Trained:
    """Initial body `name` of `config`'s run trained (no parent in either run)."""
    trained = train(config, Evolution(config).genomes[name], None)
    print(f"{name}: fitness {trained[0]:.2f} ({trained[2]:.0f} s)", file=sys.stderr, flush=True)
    return trained


def evolve(config: EvolutionConfig, initial: dict[str, Trained]) -> dict[str, object]:
    """One run of `config` with one trainer: every child in child order, the initial bodies'
    trainings `initial`."""
    evolution = Evolution(config)
    checkpoints = {name: trained[1] for name, trained in initial.items()}
    for name, (fitness, _, _) in initial.items():
        evolution.birth(name, fitness, evolution.genomes[name])
    wall = sum(trained[2] for trained in initial.values())
    repeats = 0
    start = time.perf_counter()
    while not evolution.complete:
        decided = evolution.tournament()
        assert decided is not None  # every child before it is born: its pool is known
        evolution.record(decided)
        child = decided.name
        try:
            genome, _ = evolution.body(child)
        except MutationFailed:
            evolution.give_up(child)
            continue
        earlier = evolution.repeat(child)
        if earlier is not None:
            repeats += 1
            checkpoints[child] = checkpoints[earlier]
            evolution.birth(child, evolution.fitness[earlier], genome, earlier)
            continue
        parent = evolution.parents[child]
        inherited = None
        if config.inherit == "parent" and parent is not None:
            inherited = (evolution.genomes[parent], checkpoints[parent])
        fitness, checkpoints[child], _ = train(config, genome, inherited)
        evolution.birth(child, fitness, genome)
        print(f"{config.inherit} {child}: fitness {fitness:.2f}", file=sys.stderr, flush=True)
    wall += time.perf_counter() - start
    order = sorted(evolution.fitness, key=lambda agent: evolution.index[agent])
    children = [evolution.fitness[a] for a in order if a.startswith("c")]
    return {
        "inherit": config.inherit,
        "fitness": {agent: round(evolution.fitness[agent], 4) for agent in order},
        "children_mean": statistics.fmean(children),
        "best": max(evolution.fitness.values()),
        "repeats": repeats,
        "wall_s": round(wall, 1),
    }


def interval(differences: list[float], seed: int = 0) -> dict[str, object]:
    """The mean of `differences` and a 95 % percentile bootstrap interval of it."""
    values = np.array(differences)
    rng = np.random.default_rng(seed)
    means = values[rng.integers(0, len(values), (RESAMPLES, len(values)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return {"n": len(values), "mean": float(values.mean()), "ci95": [float(low), float(high)]}


def over_seeds(means: list[float]) -> dict[str, object]:
    """The mean of the seeds' mean differences and its 95 % t interval: the seed is the unit
    (a run's children are not independent of each other: each is bred from earlier ones)."""
    mean = statistics.fmean(means)
    half = float(stats.t.ppf(0.975, len(means) - 1)) * statistics.stdev(means) / len(means) ** 0.5
    return {"n": len(means), "means": means, "mean": mean, "ci95": [mean - half, mean + half]}


def compare(size: dict[str, int], seed: int, pool: ProcessPoolExecutor) -> dict[str, object]:
    """The two runs of seed `seed` at `size`, and the differences parent - none of the fitness of
    each tournament's child, in tournament order."""
    configs = [load_profile("demo", inherit=inherit, seed=seed, **size) for inherit in INHERIT]
    names = [child.name for child in Evolution(configs[0]).initial]
    trained = pool.map(train_initial, [configs[0]] * len(names), names)
    initial = dict(zip(names, trained, strict=True))
    none, parent = pool.map(evolve, configs, [initial] * len(configs))
    assert isinstance(none["fitness"], dict) and isinstance(parent["fitness"], dict)
    tournaments = sorted(set(none["fitness"]) & set(parent["fitness"]) - set(names))
    differences = [parent["fitness"][a] - none["fitness"][a] for a in tournaments]
    return {"seed": seed, "runs": [none, parent], "differences": differences}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--total", type=int, default=24)
    parser.add_argument("--population", type=int, default=6)
    parser.add_argument("--tournament", type=int, default=3)
    parser.add_argument("--in-flight", type=int, default=3)
    parser.add_argument("--steps", type=int, default=32_768)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    args = parser.parse_args()
    size = {
        "total": args.total,
        "population": args.population,
        "tournament": args.tournament,
        "in_flight": args.in_flight,
        "train_steps": args.steps,
    }
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(len(INHERIT), mp_context=context) as pool:
        seeds = [compare(size, seed, pool) for seed in args.seeds]
    differences = [cast(list[float], one["differences"]) for one in seeds]
    pooled = [d for one in differences for d in one]
    halves = [d for one in differences for d in _last_half(one)]
    paired = {"all": interval(pooled), "last_half": interval(halves)}
    if len(seeds) > 1:
        paired["over_seeds"] = over_seeds([statistics.fmean(one) for one in differences])
    config = load_profile("demo", **size)
    print(json.dumps({
        "profile": "demo", **size, "num_envs": config.num_envs, "world": config.world,
        "seeds": seeds, "paired": paired,
    }, indent=1))  # fmt: skip


def _last_half(values: list[float]) -> list[float]:
    return values[len(values) // 2 :]


if __name__ == "__main__":
    main()
