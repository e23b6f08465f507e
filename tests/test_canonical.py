"""A body's hash is invariant to limb numbering and to which twin of a pair is stored, and tells
apart any two bodies whose physical limbs (place, direction, length, hinges) differ."""

from __future__ import annotations

import numpy as np

from derl.unimal import Genome, Joint, Limb, body_hash, canonical_form, mutate, sample_population
from derl.unimal.geometry import layout


def _round(vector: np.ndarray) -> tuple[float, ...]:
    return tuple(float(x) + 0.0 for x in np.round(vector, 6))


def _hinge(axis: np.ndarray, joint: Joint) -> tuple:
    """A hinge about `axis` with the joint's range, with the axis pointing one agreed way (a
    hinge about -a with range (lo, hi) is the hinge about a with range (-hi, -lo))."""
    a = np.round(axis, 6)
    lo, hi = joint.range
    if a[np.flatnonzero(a)[0]] < 0:
        a, lo, hi = -a, -hi, -lo
    return (_round(a), (lo, hi), joint.gear)


def _physical(genome: Genome) -> tuple:
    """The body as MuJoCo builds it, named by nothing the genome numbers: each physical limb's
    parent place, place, direction, length and hinges; and the height it stands at, where its
    genome keeps one (a `delete_limb` child: the spawn and the fall test)."""
    parts = layout(genome)
    origin = {p.name: p.origin for p in parts} | {"head": np.zeros(3)}
    limbs = sorted(
        (
            _round(origin[p.parent]),
            _round(p.origin),
            _round(p.direction),
            p.limb.length,
            tuple(sorted(_hinge(a, j) for a, j in zip(p.axes, p.limb.joints, strict=True))),
        )
        for p in parts
    )
    return (genome.head_density, genome.limb_density, tuple(limbs), genome.stand_height)


def _renumbered(genome: Genome, shift: int) -> Genome:
    """The same body with other limb ids and the entries in reverse order."""
    new = {limb.id: 100 - 7 * limb.id - shift for limb in genome.limbs}
    limbs = tuple(
        limb.model_copy(update={"id": new[limb.id], "parent": new.get(limb.parent)})
        for limb in reversed(genome.limbs)
    )
    return Genome(
        head_density=genome.head_density,
        limb_density=genome.limb_density,
        limbs=limbs,
        stand_height=genome.stand_height,
    )


def _swap_twins(genome: Genome, root: int) -> Genome:
    """The same body with the other twin of pair `root` (grown on a sagittal site) stored, and of
    every pair grown on it: mirror directions, x hinges' ranges negated."""
    subtree, grown = {root}, True
    while grown:
        grown = False
        for limb in genome.limbs:
            if limb.parent in subtree and limb.id not in subtree:
                subtree.add(limb.id)
                grown = True

    def swapped(limb: Limb) -> Limb:
        joints = tuple(
            j.model_copy(update={"range": (-j.range[1], -j.range[0])}) if j.axis == "x" else j
            for j in limb.joints
        )
        return limb.model_copy(update={"theta": (360 - limb.theta) % 360, "joints": joints})

    limbs = tuple(swapped(limb) if limb.id in subtree else limb for limb in genome.limbs)
    return genome.model_copy(update={"limbs": limbs})


def _family(n: int) -> list[Genome]:
    """Random bodies and, for each, children and grandchildren (many near-equal bodies)."""
    out = []
    for body in sample_population(n, np.random.default_rng(11)):
        out.append(body)
        rng = np.random.default_rng(len(out))
        for _ in range(6):
            child, _ = mutate(body, rng)
            out += [child, mutate(child, rng)[0]]
    return out


def test_renumbered_bodies_hash_equal() -> None:
    for genome in _family(4):
        for shift in (0, 3):
            other = _renumbered(genome, shift)
            assert _physical(other) == _physical(genome)
            assert body_hash(other) == body_hash(genome)


def test_a_pair_stored_by_its_other_twin_is_the_same_body() -> None:
    seen = 0
    for genome in _family(6):
        for limb in genome.limbs:
            if limb.paired and genome.is_sagittal(limb.parent):
                other = _swap_twins(genome, limb.id)
                assert other != genome
                assert _physical(other) == _physical(genome)  # the claim, checked on the layout
                assert body_hash(other) == body_hash(genome)
                seen += 1
    assert seen > 5


def test_the_hash_tells_bodies_apart_exactly_when_their_physics_differ() -> None:
    bodies = _family(12)
    by_hash: dict[str, tuple] = {}
    by_physics: dict[tuple, str] = {}
    for genome in bodies:
        key, physics = body_hash(genome), _physical(genome)
        assert by_hash.setdefault(key, physics) == physics
        assert by_physics.setdefault(physics, key) == key
    assert len(by_hash) > len(bodies) // 2
    assert len(by_hash) < len(bodies)  # some children undo or repeat a mutation


def test_any_physical_change_changes_the_hash() -> None:
    x = Joint(axis="x", range=(-30, 0), gear=150)
    pair = Limb(id=0, paired=True, length=0.2, theta=45, phi=90, joints=(x,))
    leg = Limb(id=1, parent=0, site="end", paired=True, length=0.2, theta=0, phi=180, joints=(x,))
    tail = Limb(id=2, length=0.3, theta=180, phi=135, joints=(x,))
    body = Genome(head_density=500, limb_density=600, limbs=(pair, leg, tail))
    flipped_x = Joint(axis="x", range=(0, 30), gear=150)
    changes = [
        body.model_copy(update={"head_density": 600}),
        body.model_copy(update={"limb_density": 500}),
        body.model_copy(update={"limbs": (pair.model_copy(update={"theta": 135}), leg, tail)}),
        body.model_copy(update={"limbs": (pair, leg.model_copy(update={"site": "mid"}), tail)}),
        body.model_copy(update={"limbs": (pair, leg.model_copy(update={"length": 0.3}), tail)}),
        body.model_copy(update={"limbs": (pair, leg, tail.model_copy(update={"phi": 90}))}),
        # the mirror image of a sagittal limb's x hinge swings to the other side
        body.model_copy(
            update={"limbs": (pair, leg, tail.model_copy(update={"joints": (flipped_x,)}))}
        ),
        body.model_copy(
            update={"limbs": (pair, leg.model_copy(update={"joints": (flipped_x,)}), tail)}
        ),
        body.model_copy(
            update={
                "limbs": (
                    pair,
                    leg,
                    tail.model_copy(update={"joints": (x.model_copy(update={"gear": 200}),)}),
                )
            }
        ),
        body.model_copy(update={"limbs": (pair, leg)}),
    ]
    hashes = {body_hash(g) for g in [body, *changes]}
    assert len(hashes) == len(changes) + 1
    for genome in changes:
        assert canonical_form(genome) != canonical_form(body)
        assert _physical(genome) != _physical(body)


def test_the_hash_is_stable() -> None:
    """Journals of old runs are matched against new bodies: the digest must not drift."""
    x = Joint(axis="x", range=(-30, 0), gear=150)
    body = Genome(
        head_density=500,
        limb_density=500,
        limbs=(Limb(id=0, length=0.2, theta=0, phi=180, joints=(x,)),),
    )
    assert body_hash(body) == "48deb9e5faa62923"
