"""How many trainings repeat detection saves: aging tournaments and breeding simulated without
training; prints JSON.

Per profile, worker count and fitness model, over seeds: W trainers each train one child at a
time (a training takes a uniform 0.5-1.5 time units), the P initial bodies first; a free trainer
gets the next tournament's child once its population is known (the profile's `in_flight`
window; free-running at 0), bred as the coordinator breeds it, and a child whose body
(`body_hash`) is born already is born at once with that body's fitness (a repeat, no training),
as the coordinator does (`Evolution.body`, then `Evolution.repeat`: their CPU time per child is
the coordinator's cost of deciding a body, `decide_ms`). With ``hold`` false a body equal to one
still in training is trained again (`trained_twice`, with the same fitness: training is
deterministic within a run); with ``hold`` true (the coordinator's policy,
`EvolutionState.hold`) a child whose body is that of a child in training waits for its birth,
then is born as its repeat, while its trainer takes the next child. Fitness models: ``random``
(every distinct body an independent N(0, 1), the default) and ``inherited`` (the parent's plus
N(0, 0.5)). The initial population is drawn once per profile (its sampling dominates the
cost); the seeds vary the tournaments, the mutations and the fitness. `saved` is repeats /
tournament children.
Run: python bench/repeats.py [--profiles demo paper] [--seeds 5] [--workers 1 2 16]
[--fitness random inherited]
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import json
import statistics
import time
from collections import deque

import numpy as np

from derl.evolution import Evolution, EvolutionConfig, load_profile
from derl.unimal import Genome, body_hash, sample_population

MODELS = ("random", "inherited")


def simulate(
    config: EvolutionConfig, initial: list[Genome], workers: int, model: str, seed: int, hold: bool
) -> dict[str, float]:
    """One run: tournament children, repeats born untrained, and equal bodies trained twice;
    `hold`: a child whose body is that of a child in training waits for its birth. Also the
    trainers' `utilisation`: their busy time over `workers` x the run's duration."""
    config = config.model_copy(update={"seed": seed})
    evolution = Evolution(config, initial)
    rng = np.random.default_rng([seed, 7])
    fitness: dict[str, float] = {}  # body hash -> its fitness (the same for the same body)
    for child in evolution.initial:
        fitness[body_hash(child.genome)] = float(rng.normal())
    running: list[tuple[float, str, Genome, str]] = []  # (finish, child, body, hash)
    training: dict[str, int] = {}  # hash -> trainings of it under way
    in_training_with: dict[str, str] = {}  # hash -> the child in training with that body
    held: dict[str, list[str]] = {}  # child in training -> the children held for it
    # children to train before any tournament (the initial bodies), then those released by a
    # birth (looked up again first)
    waiting: deque[str] = deque(child.name for child in evolution.initial)
    repeats = in_training = 0
    costs: list[float] = []  # CPU s to breed and look up a child (the coordinator's, per child)
    now, idle, busy = 0.0, workers, 0.0

    def next_child() -> str | None:
        if waiting:
            return waiting.popleft()
        started = evolution.settled + len(running) + sum(map(len, held.values()))
        if started >= config.total:
            return None
        decided = evolution.tournament()
        if decided is None:  # its population is not known yet
            return None
        evolution.record(decided)
        return decided.name

    def assign() -> bool:
        nonlocal repeats, in_training, busy
        while (name := next_child()) is not None:
            start = time.thread_time()
            body, _ = evolution.body(name)  # as the coordinator breeds it and looks it up
            earlier = evolution.repeat(name)
            costs.append(time.thread_time() - start)
            if earlier is not None:
                evolution.birth(name, evolution.fitness[earlier], body, earlier)
                repeats += 1
                continue
            key = evolution.body_key(name)
            if hold and in_training_with.get(key, name) != name:
                held.setdefault(in_training_with[key], []).append(name)
                continue
            in_training_with.setdefault(key, name)
            in_training += training.get(key, 0) > 0
            training[key] = training.get(key, 0) + 1
            if key not in fitness:
                parent = evolution.parents[name]
                base = evolution.fitness[parent] if model == "inherited" else 0.0
                fitness[key] = base + float(rng.normal(0.0, 0.5 if model == "inherited" else 1.0))
            duration = rng.uniform(0.5, 1.5)
            busy += duration
            heapq.heappush(running, (now + duration, name, body, key))
            return True
        return False

    def dispatch() -> None:
        nonlocal idle
        while idle and assign():
            idle -= 1

    dispatch()
    while running:
        now, name, body, key = heapq.heappop(running)
        idle += 1
        training[key] -= 1
        evolution.birth(name, fitness[key], body)
        if in_training_with.get(key) == name:
            del in_training_with[key]
        waiting.extendleft(reversed(held.pop(name, [])))
        dispatch()
    assert evolution.complete and not held and not waiting
    return {
        "children": config.total - config.population,
        "repeats": repeats,
        "in_training": in_training,
        "decide_ms": [c * 1e3 for c in costs],
        "utilisation": busy / (workers * now),
    }


def bench(
    profiles: list[str], seeds: int, workers: list[int], models: list[str]
) -> list[dict[str, object]]:
    results = []
    for profile in profiles:
        config = load_profile(profile, [("timing", "window")])
        start = time.perf_counter()
        initial = sample_population(config.population, np.random.default_rng([config.seed, 0]))
        sampled_s = time.perf_counter() - start
        for count, model, hold in itertools.product(workers, models, (False, True)):
            runs = [simulate(config, initial, count, model, seed, hold) for seed in range(seeds)]
            saved = [r["repeats"] / r["children"] for r in runs]
            decide = sorted(ms for r in runs for ms in r["decide_ms"])
            results.append(
                {
                    "profile": config.name,
                    "population": config.population,
                    "tournament": config.tournament,
                    "total": config.total,
                    "workers": count,
                    "fitness": model,
                    "hold": hold,
                    "children": runs[0]["children"],
                    "repeats_median": statistics.median(r["repeats"] for r in runs),
                    "saved_median": round(statistics.median(saved), 4),
                    "saved_range": [round(min(saved), 4), round(max(saved), 4)],
                    "trained_twice_median": statistics.median(r["in_training"] for r in runs),
                    "repeats": [r["repeats"] for r in runs],
                    "decide_ms": {
                        "median": round(statistics.median(decide), 2),
                        "p99": round(decide[int(0.99 * (len(decide) - 1))], 2),
                        "max": round(decide[-1], 2),
                    },
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
    parser.add_argument("--fitness", nargs="+", choices=MODELS, default=["random"])
    args = parser.parse_args()
    bench(args.profiles, args.seeds, args.workers, args.fitness)


if __name__ == "__main__":
    main()
