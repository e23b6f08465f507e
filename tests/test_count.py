"""The design-space count agrees with brute-force enumeration on a reduced space."""

from __future__ import annotations

from derl.unimal import Genome, Joint, Limb, body_hash
from derl.unimal.count import _bodies, count_design_space, joint_configurations
from derl.unimal.mutations import (
    PAIR_ON_PAIR_DIRECTIONS,
    PAIR_ON_SAGITTAL_DIRECTIONS,
    SAGITTAL_DIRECTIONS,
)

JOINTS = (Joint(axis="x", range=(-30, 0), gear=150),)


def _grown(genome: Genome) -> list[Genome]:
    """Every genome one entry larger, trying all sites and directions (one parameter set)."""
    sites: list[tuple[int | None, str]] = [(None, "head")]
    sites += [(limb.id, s) for limb in genome.limbs for s in ("mid", "end")]
    out = []
    for parent, site in sites:
        options = (
            [(False, d) for d in SAGITTAL_DIRECTIONS]
            + [(True, d) for d in PAIR_ON_SAGITTAL_DIRECTIONS]
            if genome.is_sagittal(parent)
            else [(True, d) for d in PAIR_ON_PAIR_DIRECTIONS]
        )
        taken = {(c.theta, c.phi) for c in genome.children(parent) if c.site == site}
        for paired, (theta, phi) in options:
            if (theta, phi) in taken:
                continue
            limb = Limb(
                id=genome.next_id(),
                parent=parent,
                site=site,
                paired=paired,
                length=0.2,
                theta=theta,
                phi=phi,
                joints=JOINTS,
            )
            try:
                out.append(Genome(head_density=500, limb_density=500, limbs=(*genome.limbs, limb)))
            except ValueError:
                continue
    return out


def test_generating_functions_match_enumeration() -> None:
    max_limbs = 3
    frontier = [Genome(head_density=500, limb_density=500)]
    seen: dict[str, int] = {}
    while frontier:
        genome = frontier.pop()
        key = body_hash(genome)
        if key in seen or genome.num_limbs > max_limbs:
            continue
        seen[key] = genome.num_limbs
        frontier.extend(g for g in _grown(genome) if g.num_limbs <= max_limbs)
    by_limbs = [sum(1 for n in seen.values() if n == k) for k in range(max_limbs + 1)]
    assert by_limbs == _bodies(1, max_limbs)
    assert by_limbs[1] == len(SAGITTAL_DIRECTIONS)


def test_full_count_is_reported_against_the_paper() -> None:
    count = count_design_space()
    assert joint_configurations() == 2 * 13 * 4 + (13 * 4) ** 2
    assert count.total == sum(count.by_limbs[1:])
    assert count.total > 1e18  # the paper's estimate is a lower bound of the full space
    assert count.shapes < count.total
