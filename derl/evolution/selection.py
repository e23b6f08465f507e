"""Selection schemes: how a tournament chooses its parent from the population, an extension
point (`SELECTION_REGISTRY`, entry point group ``derl.selection``).

A scheme sees only the pool (the births a tournament may draw from: `Member`s with their fitness
and cost of work) and the tournament's seeded draws (`Draws`), so the run stays a function of its
seed. It returns the parent and the contestants it compared (`Selected`), which the coordinator
journals as the tournament. Built in:

- ``tournament`` (the paper's, the default): T contestants drawn with replacement, the fittest
  is the parent, the first drawn among equals.
- ``pareto``: the same T contestants; the parent is drawn uniformly from those no other
  contestant beats on both fitness (higher) and cost of work (lower; an undefined cost counts
  as the worst), a Pareto tournament on the two (cheaper walkers of equal speed survive).

A plugin scheme is a factory (a class, or a function) called with the profile's
``selection_options`` as keywords, which returns a callable ``(pool, draws) -> Selected``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np

from derl.evolution.member import Member
from derl.plugins import PluginError, Registry


@dataclass(frozen=True)
class Draws:
    """A tournament's seeded randomness: `positions`, the T positions in the pool drawn with
    replacement (the paper's contestants), and `rng`, a generator seeded from the run's seed
    and the tournament's number, for a scheme that needs more."""

    positions: tuple[int, ...]
    seed: int
    iteration: int

    @cached_property
    def rng(self) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.iteration, 1])


@dataclass(frozen=True)
class Selected:
    """A tournament's outcome: the parent, and the contestants it was chosen among."""

    parent: Member
    contestants: tuple[Member, ...]


class Selection(Protocol):
    """Chooses a tournament's parent: a pure function of the pool and the draws."""

    def __call__(self, pool: Sequence[Member], draws: Draws) -> Selected: ...


def tournament() -> Selection:
    """The paper's aging tournament: the fittest of the T drawn (the first drawn among equals)."""

    def select(pool: Sequence[Member], draws: Draws) -> Selected:
        drawn = tuple(pool[i] for i in draws.positions)
        return Selected(max(drawn, key=lambda m: m.fitness), drawn)

    return select


def pareto() -> Selection:
    """A Pareto tournament on fitness (higher) and cost of work (lower): a parent drawn uniformly
    from the drawn contestants that no other one dominates."""

    def select(pool: Sequence[Member], draws: Draws) -> Selected:
        drawn = tuple(pool[i] for i in draws.positions)
        costs = [m.cost_of_work if math.isfinite(m.cost_of_work) else math.inf for m in drawn]

        def dominated(k: int) -> bool:
            return any(
                other.fitness >= drawn[k].fitness
                and costs[j] <= costs[k]
                and (other.fitness > drawn[k].fitness or costs[j] < costs[k])
                for j, other in enumerate(drawn)
            )

        front = [m for k, m in enumerate(drawn) if not dominated(k)]
        return Selected(front[int(draws.rng.integers(len(front)))], drawn)

    return select


def _scheme_factory(loaded: object) -> Callable[..., Selection]:
    if not callable(loaded):
        raise TypeError(f"{loaded!r} is not callable")
    return loaded


SCHEMES: dict[str, Callable[..., Selection]] = {"tournament": tournament, "pareto": pareto}
"""The built-in schemes' factories."""
SELECTION_REGISTRY: Registry[Callable[..., Selection]] = Registry(
    "selection", "derl.selection", SCHEMES, _scheme_factory
)
"""Every selection scheme's factory by name: the built-ins and the plugins."""


def make_selection(name: str, options: Mapping[str, object] | None = None) -> Selection:
    """The scheme `name` made with `options` (`PluginError` saying why it cannot be)."""
    factory = SELECTION_REGISTRY.get(name)
    try:
        scheme = factory(**(options or {}))
    except Exception as error:  # a plugin's factory may raise anything
        raise PluginError(f"selection {name!r} could not be made with {options}: {error}") from None
    if not callable(scheme):
        raise PluginError(f"selection {name!r} made {scheme!r}, which is not callable")
    return scheme


def select(name: str, scheme: Selection, pool: Sequence[Member], draws: Draws) -> Selected:
    """`scheme`'s choice, checked: `PluginError` unless the parent and every contestant are
    agents of `pool` (the pool's own members are kept: a scheme cannot alter what it read)."""
    try:
        chosen = scheme(pool, draws)
    except Exception as error:  # a plugin may raise anything
        raise PluginError(f"selection {name!r} raised {type(error).__name__}: {error}") from None
    if not isinstance(chosen, Selected):
        raise PluginError(f"selection {name!r} returned {chosen!r}, not a Selected")
    if not chosen.contestants:
        raise PluginError(f"selection {name!r} compared no contestants")
    members = {m.agent: m for m in pool}

    def member(chosen: object) -> Member:
        agent = getattr(chosen, "agent", chosen)
        if not isinstance(agent, str) or agent not in members:
            raise PluginError(
                f"selection {name!r} chose {agent!r}, which is not in the pool it was given"
            )
        return members[agent]

    return Selected(member(chosen.parent), tuple(member(m) for m in chosen.contestants))
