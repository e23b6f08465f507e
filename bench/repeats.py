"""How many trainings repeat detection saves: aging tournaments and breeding simulated without
training; prints JSON.

Per profile, worker count and fitness model, over seeds: W trainers each train one child at a
time (a training takes a uniform 0.5-1.5 time units), the P initial bodies first; a free trainer
gets the next tournament's child, bred as the coordinator breeds it, and a child whose body
(`body_hash`) is born already is born at once with that body's fitness (a repeat, no training),
as the coordinator does (`Evolution.repeat`; `missed`: born bodies it did not see, their first
draft being invalid). A body equal to one still in training is trained again (`in_training`),
with the same fitness (training is deterministic within a run). Fitness models: ``random`` (every
distinct body an independent N(0, 1)) and ``inherited`` (the parent's plus N(0, 0.5)). The
initial population is drawn once per profile (its sampling dominates the cost); the seeds vary
the tournaments, the mutations and the fitness. `saved` is repeats / tournament children.
Run: python bench/repeats.py [--profiles demo paper] [--seeds 5] [--workers 1 2 16]
"""

from __future__ import annotations

import argparse
import heapq
import json
import statistics
import time

import numpy as np

from derl.evolution import Evolution, EvolutionConfig, breed, load_profile
from derl.unimal import Genome, body_hash, sample_population

MODELS = ("random", "inherited")


def simulate(
    config: EvolutionConfig, initial: list[Genome], workers: int, model: str, seed: int
) -> dict[str, float]:
    """One run: tournament children, repeats born untrained, and equal bodies trained twice."""
    config = config.model_copy(update={"seed": seed})
    evolution = Evolution(config, initial)
    rng = np.random.default_rng([seed, 7])
    fitness: dict[str, float] = {}  # body hash -> its fitness (the same for the same body)
    for child in evolution.initial:
        fitness[body_hash(child.genome)] = float(rng.normal())
    order = [child.name for child in evolution.initial]
    for name in rng.permutation(order):  # the initial bodies finish in random order
        genome = evolution.genomes[name]
        evolution.birth(str(name), fitness[body_hash(genome)], genome)
    running: list[tuple[float, str, Genome, str]] = []  # (finish, child, body, hash)
    training: dict[str, int] = {}  # hash -> trainings of it under way
    repeats = missed = in_training = 0
    lookups: list[float] = []  # s per `Evolution.repeat` (the coordinator's cost per child)
    now = 0.0

    def assign() -> bool:
        nonlocal repeats, missed, in_training
        while evolution.settled + len(running) < config.total:
            decided = evolution.tournament()
            evolution.record(decided)
            start = time.perf_counter()
            repeat = evolution.repeat(decided.name)  # as the coordinator looks it up
            lookups.append(time.perf_counter() - start)
            if repeat is not None:
                earlier, body, _ = repeat
                evolution.birth(decided.name, evolution.fitness[earlier], body, earlier)
                repeats += 1
                continue
            body = breed(*evolution.to_train(decided.name))[0]
            missed += evolution.repeat_of(body) is not None  # its first draft was invalid
            key = body_hash(body)
            in_training += training.get(key, 0) > 0
            training[key] = training.get(key, 0) + 1
            if key not in fitness:
                base = evolution.fitness[decided.parent] if model == "inherited" else 0.0
                fitness[key] = base + float(rng.normal(0.0, 0.5 if model == "inherited" else 1.0))
            heapq.heappush(running, (now + rng.uniform(0.5, 1.5), decided.name, body, key))
            return True
        return False

    for _ in range(workers):
        if not assign():
            break
    while running:
        now, name, body, key = heapq.heappop(running)
        training[key] -= 1
        evolution.birth(name, fitness[key], body)
        assign()
    children = config.total - config.population
    return {
        "children": children,
        "repeats": repeats,
        "missed": missed,
        "in_training": in_training,
        "lookup_ms": statistics.median(lookups) * 1e3,
    }


def bench(profiles: list[str], seeds: int, workers: list[int]) -> list[dict[str, object]]:
    results = []
    for profile in profiles:
        config = load_profile(profile)
        start = time.perf_counter()
        initial = sample_population(config.population, np.random.default_rng([config.seed, 0]))
        sampled_s = time.perf_counter() - start
        for count in workers:
            for model in MODELS:
                runs = [simulate(config, initial, count, model, seed) for seed in range(seeds)]
                saved = [r["repeats"] / r["children"] for r in runs]
                results.append(
                    {
                        "profile": config.name,
                        "population": config.population,
                        "tournament": config.tournament,
                        "total": config.total,
                        "workers": count,
                        "fitness": model,
                        "children": runs[0]["children"],
                        "repeats_median": statistics.median(r["repeats"] for r in runs),
                        "saved_median": round(statistics.median(saved), 4),
                        "saved_range": [round(min(saved), 4), round(max(saved), 4)],
                        "missed_median": statistics.median(r["missed"] for r in runs),
                        "trained_twice_median": statistics.median(r["in_training"] for r in runs),
                        "repeats": [r["repeats"] for r in runs],
                        "lookup_ms_median": round(
                            statistics.median(r["lookup_ms"] for r in runs), 3
                        ),
                        "initial_sampling_s": round(sampled_s, 1),
                    }
                )
                print(json.dumps(results[-1]), flush=True)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profiles", nargs="+", default=["demo", "paper"])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 16])
    args = parser.parse_args()
    bench(args.profiles, args.seeds, args.workers)


if __name__ == "__main__":
    main()
