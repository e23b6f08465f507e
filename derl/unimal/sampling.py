"""Random initial bodies and populations: a target limb count uniform in {2..8}, reached by
random mutations after a first growth (as the original), and a population without near-duplicates.

Two bodies are near-duplicates when they have the same multiset of limb directions: the original's
"species" criterion (equal limb count and Hungarian-matched limb orientation matrices closer than
0.2), which on the design space's discrete angles holds exactly when the multisets are equal.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from derl.unimal.genome import Genome
from derl.unimal.mutations import MutationFailed, mutate
from derl.unimal.space import DENSITIES

MIN_TARGET_LIMBS = 2
MAX_TARGET_LIMBS = 8
MAX_MUTATIONS = 500


def random_genome(rng: np.random.Generator) -> Genome:
    """One valid random body with a limb count drawn uniformly from {2..8} (a pair may add one)."""
    target = int(rng.integers(MIN_TARGET_LIMBS, MAX_TARGET_LIMBS + 1))
    while True:
        genome = Genome(
            head_density=DENSITIES[int(rng.integers(len(DENSITIES)))],
            limb_density=DENSITIES[int(rng.integers(len(DENSITIES)))],
        )
        for _ in range(MAX_MUTATIONS):
            try:
                genome, _ = mutate(genome, rng, op=None if genome.limbs else "grow_limb")
            except MutationFailed:
                continue
            if genome.num_limbs >= target:
                return genome


def shape_key(genome: Genome) -> tuple[tuple[int, int], ...]:
    """The multiset of physical limb directions (theta, phi), mirror twins included."""
    directions: list[tuple[int, int]] = []
    for limb in genome.limbs:
        directions.append((limb.theta, limb.phi))
        if limb.paired:
            directions.append(((360 - limb.theta) % 360, limb.phi))
    return tuple(sorted(directions))


def iter_population(rng: np.random.Generator) -> Iterator[Genome]:
    """Random bodies, each unlike all before it (no two with the same `shape_key`)."""
    seen: set[tuple[tuple[int, int], ...]] = set()
    while True:
        genome = random_genome(rng)
        key = shape_key(genome)
        if key not in seen:
            seen.add(key)
            yield genome


def sample_population(n: int, rng: np.random.Generator) -> list[Genome]:
    """`n` random bodies with no near-duplicates."""
    population = iter_population(rng)
    return [next(population) for _ in range(n)]
