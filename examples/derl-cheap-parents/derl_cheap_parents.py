"""A selection scheme for derl: the paper's tournament, scored by fitness less a penalty on the
cost of work (energy per unit of progress), so that of two equally fit bodies the one that walks
more cheaply becomes the parent.

    selection: cheap_parents
    selection_options: {penalty: 20.0}

A scheme sees only the pool and the tournament's seeded draws, so the run stays a function of
its seed; derl checks that what it returns is in the pool.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from derl.evolution.member import Member
from derl.evolution.selection import Draws, Selected, Selection


def cheap_parents(penalty: float = 10.0) -> Selection:
    """The fittest of the T drawn by ``fitness - penalty x cost_of_work`` (an undefined cost of
    work, a body that made no progress, counts as the largest drawn)."""
    if penalty < 0:
        raise ValueError(f"penalty must be >= 0, not {penalty}")

    def select(pool: Sequence[Member], draws: Draws) -> Selected:
        drawn = tuple(pool[i] for i in draws.positions)
        finite = [m.cost_of_work for m in drawn if math.isfinite(m.cost_of_work)]
        worst = max(finite, default=0.0)

        def score(member: Member) -> float:
            cost = member.cost_of_work if math.isfinite(member.cost_of_work) else worst
            return member.fitness - penalty * cost

        return Selected(max(drawn, key=score), drawn)

    return select
