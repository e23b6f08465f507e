"""A born agent as evolution sees it: what a tournament compares."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Member:
    """A born agent."""

    agent: str
    fitness: float
    parent: str | None
    birth: int
    repeat_of: str | None = None  # the earlier agent with this body, whose result it took
    cost_of_work: float = float("nan")  # of its training (NaN: undefined, see derl.lifetime)
