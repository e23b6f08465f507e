"""Reference bodies for the benchmarks: a 6-limb and a 10-limb UNIMAL, the same on every run."""

from __future__ import annotations

import numpy as np

from derl.unimal import Genome, MutationFailed, mutate, random_genome


def reference_body(limbs: int, seed: int = 0) -> Genome:
    """The first random body (from `seed`) grown or drawn to exactly `limbs` limbs."""
    rng = np.random.default_rng(seed)
    while True:
        genome = random_genome(rng)
        while genome.num_limbs < limbs:
            try:
                genome, _ = mutate(genome, rng, op="grow_limb")
            except MutationFailed:
                break
        if genome.num_limbs == limbs:
            return genome
