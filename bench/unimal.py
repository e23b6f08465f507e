"""Benchmark of the UNIMAL design space; prints JSON.

Measures, as medians over repeats: random bodies sampled per second (with near-duplicate
rejection), one mutation including its full validity check (the original took about 180 ms per
grow_limb), MJCF compilation of a body alone, and the 400-step passive-stability test.
Run: python bench/unimal.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import mujoco
import numpy as np

from derl.unimal import MutationFailed, describe, mutate, random_genome, sample_population
from derl.unimal.mjcf import agent_spec


def _median_ms(samples: list[float]) -> float:
    return round(statistics.median(samples) * 1e3, 3)


def bench(repeats: int) -> dict[str, object]:
    rng = np.random.default_rng(0)
    sampling_rates = []
    for _ in range(repeats):
        start = time.perf_counter()
        sample_population(20, rng)
        sampling_rates.append(20 / (time.perf_counter() - start))

    bodies = [random_genome(rng) for _ in range(30)]
    per_op: dict[str, list[float]] = {}
    failures = 0
    for _ in range(repeats):
        for genome in bodies:
            for _ in range(10):
                start = time.perf_counter()
                try:
                    _, mutation = mutate(genome, rng)
                except MutationFailed:
                    failures += 1
                    continue
                per_op.setdefault(mutation.op, []).append(time.perf_counter() - start)
    all_mutations = [t for times in per_op.values() for t in times]

    compile_times = []
    for genome in bodies:
        start = time.perf_counter()
        agent_spec(genome).compile()
        compile_times.append(time.perf_counter() - start)

    describe_times = []
    for genome in bodies[:10]:
        start = time.perf_counter()
        describe(genome)
        describe_times.append(time.perf_counter() - start)

    return {
        "mujoco": mujoco.__version__,
        "repeats": repeats,
        "bodies_sampled_per_s": round(statistics.median(sampling_rates), 1),
        "mutation_with_validity_ms_median": _median_ms(all_mutations),
        "mutation_with_validity_ms_p90": round(float(np.percentile(all_mutations, 90)) * 1e3, 3),
        "mutations_per_s": round(1 / statistics.median(all_mutations), 1),
        "mutation_ms_median_by_op": {op: _median_ms(t) for op, t in sorted(per_op.items())},
        "mutation_failures": failures,
        "mjcf_compile_ms_median": _median_ms(compile_times),
        "describe_with_stability_ms_median": _median_ms(describe_times),
        "target_mutation_ms": 5.0,
        "original_grow_limb_ms": 180.0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    print(json.dumps(bench(parser.parse_args().repeats), indent=2))


if __name__ == "__main__":
    main()
