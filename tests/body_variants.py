"""Distinct bodies for hand-built runs: a body is its `body_hash`, so records that stand for
different bodies need different genomes (real runs never draw one body twice)."""

from __future__ import annotations

from itertools import product

from derl.unimal import Genome
from derl.unimal.space import DENSITIES, GEARS


def variants(genome: Genome, n: int) -> list[Genome]:
    """`n` different bodies of `genome`'s shape: its densities and its first two limbs' gears
    changed (576 at most)."""
    first, second = genome.limbs[0], genome.limbs[1]
    combos = product(DENSITIES, DENSITIES, GEARS, GEARS)
    bodies = []
    for (head, limb, a, b), _ in zip(combos, range(n), strict=False):
        limbs = (
            first.model_copy(
                update={"joints": tuple(j.model_copy(update={"gear": a}) for j in first.joints)}
            ),
            second.model_copy(
                update={"joints": tuple(j.model_copy(update={"gear": b}) for j in second.joints)}
            ),
            *genome.limbs[2:],
        )
        bodies.append(
            genome.model_copy(update={"head_density": head, "limb_density": limb, "limbs": limbs})
        )
    if len(bodies) < n:
        raise ValueError(f"{n} variants asked for, {len(bodies)} possible")
    return bodies
