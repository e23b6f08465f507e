"""A mutation operator for derl: one limb's motors (and its mirror twin's: a pair shares one
limb entry) move one gear up the paper's gear table.

    mutations: {stiffen: 2, grow_limb: 1, delete_limb: 1, limb_params: 1, density: 1, dof: 1,
                joint_angle: 1, gear: 1}

An operator is a function ``(genome, rng) -> (child, detail)`` drawing only from `rng` (so a
child is a function of the run's seed); its ``applies`` says which bodies it can act on. derl
checks every child it makes (the body's validity: symmetry, no collisions at rest) and draws again
when one fails.
"""

from __future__ import annotations

import numpy as np

from derl.unimal.genome import Genome
from derl.unimal.space import GEARS


def stiffen(genome: Genome, rng: np.random.Generator) -> tuple[Genome, str]:
    """One limb entry drawn among those with a motor below the strongest gear: each of its
    joints one gear up."""
    weak = [limb for limb in genome.limbs if any(j.gear < max(GEARS) for j in limb.joints)]
    limb = weak[int(rng.integers(len(weak)))]
    joints = tuple(
        j.model_copy(update={"gear": min(g for g in GEARS if g > j.gear)})
        if j.gear < max(GEARS)
        else j
        for j in limb.joints
    )
    limbs = tuple(
        item.model_copy(update={"joints": joints}) if item.id == limb.id else item
        for item in genome.limbs
    )
    return genome.model_copy(update={"limbs": limbs}), f"limb {limb.id} one gear up"


def _applies(genome: Genome) -> bool:
    return any(j.gear < max(GEARS) for limb in genome.limbs for j in limb.joints)


stiffen.applies = _applies  # type: ignore[attr-defined]
