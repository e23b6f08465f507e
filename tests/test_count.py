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


def _enumerated(max_limbs: int) -> list[Genome]:
    """Every distinct shape with up to `max_limbs` limbs (one parameter set), grown one entry
    at a time from the bare head."""
    frontier = [Genome(head_density=500, limb_density=500)]
    seen: dict[str, Genome] = {}
    while frontier:
        genome = frontier.pop()
        key = body_hash(genome)
        if key in seen or genome.num_limbs > max_limbs:
            continue
        seen[key] = genome
        frontier.extend(g for g in _grown(genome) if g.num_limbs <= max_limbs)
    return list(seen.values())


def test_generating_functions_match_enumeration() -> None:
    max_limbs = 3
    shapes = _enumerated(max_limbs)
    by_limbs = [sum(1 for g in shapes if g.num_limbs == k) for k in range(max_limbs + 1)]
    assert by_limbs == _bodies(1, max_limbs)
    assert by_limbs[1] == len(SAGITTAL_DIRECTIONS)


# A limb entry (one limb, or a mirrored pair sharing its parameters) takes one of 3 lengths and
# one hinge set: an x or a y hinge, or both, each hinge with one of 13 ranges and 4 gears; the
# head and the limbs take one of 6 densities each (the space's table, written out here).
PER_ENTRY = 3 * (2 * 13 * 4 + (13 * 4) ** 2)
DENSITIES = 6 * 6
DESIGN_SPACE = 16683147686647316514881927954900496406554082373004000
"""Bodies with 1 to 10 limbs, as counted when this test was written; its terms up to 3 limbs are
checked by enumeration below (the paper's estimate, 1e18, bounds the space from below)."""
SHAPES = 373308373748  # bodies told apart by tree and directions only, 1 to 10 limbs


def test_full_count_is_reported_against_the_paper() -> None:
    """Each enumerated shape is as many bodies as its entries' parameter choices times the
    densities: the count's first terms exactly, and the whole count pinned."""
    assert joint_configurations() == 2 * 13 * 4 + (13 * 4) ** 2
    shapes = _enumerated(3)
    expected = [
        DENSITIES * sum(PER_ENTRY ** len(g.limbs) for g in shapes if g.num_limbs == n)
        for n in range(4)
    ]
    assert count_design_space(3).by_limbs == expected
    count = count_design_space()
    assert count.max_limbs == 10 and count.by_limbs[:4] == expected
    assert count.total == sum(count.by_limbs[1:]) == DESIGN_SPACE
    assert count.shapes == SHAPES
