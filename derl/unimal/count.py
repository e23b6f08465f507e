"""How many distinct bodies the design space holds, counted exactly with generating functions.

A body is a head whose centre site holds a set of limb entries, each entry's mid and end sites
holding sets of entries in turn. Counted under the genome's structural rules (symmetry, no limb
along its parent) with at most one entry per direction at a site (two limbs with one direction on
one site would overlap); other self-collisions are not modelled, so this is an upper estimate.
Polynomials are lists of exact integer coefficients indexed by the number of physical limbs.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

from derl.unimal.mutations import (
    PAIR_ON_PAIR_DIRECTIONS,
    PAIR_ON_SAGITTAL_DIRECTIONS,
    SAGITTAL_DIRECTIONS,
    Direction,
)
from derl.unimal.space import (
    AXIS_SETS,
    DENSITIES,
    GEARS,
    JOINT_RANGES,
    LIMB_LENGTHS,
    MAX_LIMBS,
)

Poly = list[int]


class DesignSpaceCount(BaseModel):
    """Distinct bodies with 1..max_limbs limbs."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_limbs: int
    by_limbs: list[int]  # index n: bodies with exactly n limbs (index 0 unused)
    total: int
    shapes: int  # bodies told apart by tree and directions only (one parameter set per limb)


def joint_configurations() -> int:
    """Hinge sets of one limb: each axis set, each hinge with its own range and gear."""
    per_hinge = len(JOINT_RANGES) * len(GEARS)
    return sum(per_hinge ** len(axes) for axes in AXIS_SETS)


def count_design_space(max_limbs: int = MAX_LIMBS) -> DesignSpaceCount:
    per_limb = len(LIMB_LENGTHS) * joint_configurations()
    densities = len(DENSITIES) ** 2
    by_limbs = [c * densities for c in _bodies(per_limb, max_limbs)]
    shapes = sum(_bodies(1, max_limbs)[1:])
    return DesignSpaceCount(
        max_limbs=max_limbs, by_limbs=by_limbs, total=sum(by_limbs[1:]), shapes=shapes
    )


def _bodies(params: int, n: int) -> Poly:
    """Coefficients of the head's generating function for `params` choices per limb entry."""
    single: dict[Direction, Poly] = {d: [0] * (n + 1) for d in SAGITTAL_DIRECTIONS}
    pair_s: dict[Direction, Poly] = {d: [0] * (n + 1) for d in PAIR_ON_SAGITTAL_DIRECTIONS}
    pair_p: dict[Direction, Poly] = {d: [0] * (n + 1) for d in PAIR_ON_PAIR_DIRECTIONS}
    for _ in range(n):  # each pass fixes one more degree of every polynomial
        single = {d: _entry(1, params, _sagittal_sites(d, single, pair_s, n), n) for d in single}
        pair_s = {d: _entry(2, params, _paired_sites(d, pair_p, n), n) for d in pair_s}
        pair_p = {d: _entry(2, params, _paired_sites(d, pair_p, n), n) for d in pair_p}
    return _site({**single, **pair_s}, n)


def _allowed(child: Direction, parent: Direction, site: str) -> bool:
    same = child == parent
    opposite = child[1] == parent[1] == 90 and (child[0] - parent[0]) % 360 == 180
    return not opposite and not (same and site == "mid")


def _sagittal_sites(
    parent: Direction, single: dict[Direction, Poly], pair_s: dict[Direction, Poly], n: int
) -> list[Poly]:
    options = {**single, **pair_s}
    return [_site({d: p for d, p in options.items() if _allowed(d, parent, s)}, n) for s in _SITES]


def _paired_sites(parent: Direction, pair_p: dict[Direction, Poly], n: int) -> list[Poly]:
    return [_site({d: p for d, p in pair_p.items() if _allowed(d, parent, s)}, n) for s in _SITES]


_SITES = ("mid", "end")


def _entry(size: int, params: int, sites: list[Poly], n: int) -> Poly:
    """x^size · params · (product of the sites' polynomials)."""
    product = _product(sites, n)
    return [0] * size + [params * c for c in product[: n + 1 - size]]


def _site(options: dict[Direction, Poly], n: int) -> Poly:
    """Generating function of a site holding at most one entry per direction."""
    return _product([[1 + p[0], *p[1:]] for p in options.values()], n)


def _product(polys: list[Poly], n: int) -> Poly:
    result = [1] + [0] * n
    for poly in polys:
        result = [sum(result[i] * poly[k - i] for i in range(k + 1)) for k in range(n + 1)]
    return result
