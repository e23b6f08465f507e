"""A body's identity: a canonical form of its genome, and a stable hash of it.

Two genomes are the same body when they differ only in limb ids and the order of the limb entries,
or in which twin of a mirror pair grown on a sagittal site is the stored (primary) one: that pair
and every pair grown on it then store the mirror direction (theta -> 360 - theta), and each x
hinge the negated range, since the mirror image of an x hinge axis is the twin's axis reversed
(`derl.unimal.geometry`); y hinges keep theirs. Everything else that shapes the body's physics is
in the form: both densities, and per entry its site, pairing, length, direction and hinges (axis,
range, gear), with the entries grown on it; and last the stand height where the genome sets one
(`Genome.stand_height`: it moves the spawn and the fall test), so that the forms and hashes of
bodies without one are those they had before the field existed. `canonical_genome` writes the
form back as a genome: its limbs numbered in the form's order, each stored twin the form's, so
that equal bodies are equal genomes and build the same model with its limbs, observations and
actions in one order.
"""

from __future__ import annotations

import hashlib

from derl.unimal.genome import Genome, Joint, Limb

Form = tuple


def canonical_form(genome: Genome) -> Form:
    """The genome as nested sorted tuples, equal exactly for equal bodies."""
    form = (genome.head_density, genome.limb_density, _children(genome, None, mirrored=False))
    return form if genome.stand_height is None else (*form, genome.stand_height)


def body_hash(genome: Genome) -> str:
    """A stable 64-bit hex digest of `canonical_form` (equal bodies, equal hashes)."""
    return hashlib.sha256(repr(canonical_form(genome)).encode()).hexdigest()[:16]


def canonical_genome(genome: Genome) -> Genome:
    """The same body as one genome for all its numberings: `canonical_form` written back, limb
    ids in its depth-first order (`canonical_form` of the result is `genome`'s)."""
    head_density, limb_density, children, *stand = canonical_form(genome)
    limbs: list[Limb] = []

    def write(forms: Form, parent: int | None) -> None:
        for site, paired, length, theta, phi, joints, grown in forms:
            limb = Limb(
                id=len(limbs),
                parent=parent,
                site=site,
                paired=paired,
                length=length,
                theta=theta,
                phi=phi,
                joints=tuple(Joint(axis=a, range=r, gear=g) for a, r, g in joints),
            )
            limbs.append(limb)
            write(grown, limb.id)

    write(children, None)
    return Genome(
        head_density=head_density,
        limb_density=limb_density,
        limbs=tuple(limbs),
        stand_height=stand[0] if stand else None,
    )


def _children(genome: Genome, parent: int | None, mirrored: bool) -> Form:
    forms = []
    for limb in genome.children(parent):
        if limb.paired and genome.is_sagittal(parent):  # either twin may be the stored one
            forms.append(min(_entry(genome, limb, False), _entry(genome, limb, True)))
        else:
            forms.append(_entry(genome, limb, mirrored))
    return tuple(sorted(forms))


def _entry(genome: Genome, limb: Limb, mirrored: bool) -> Form:
    theta = (360 - limb.theta) % 360 if mirrored else limb.theta
    joints = tuple(
        (j.axis, (-j.range[1], -j.range[0]) if mirrored and j.axis == "x" else j.range, j.gear)
        for j in limb.joints
    )
    return (
        limb.site,
        limb.paired,
        limb.length,
        theta,
        limb.phi,
        joints,
        _children(genome, limb.id, mirrored),
    )
