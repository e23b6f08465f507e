"""The plain records the analyses work on: one run's bodies in birth order and its test results.

Whoever reads a run builds these (`nodes/journal/history.py` folds the coordinator's journal into
them); nothing here knows about messages, the bus or MCAP. A body's `birth` is its place in the
run's birth order, the analyses' time axis: the order children were bred (child order, the same in
every run of a profile and seed, whatever order their trainings finished in).

A body is identified by `derl.unimal.body_hash` of its genome (the same body whatever its limbs'
numbering): a birth whose body was born before in the run (a repeat, `Body.repeat_of`) is that
body again, and the analyses that are about bodies rather than births count it once, as its
first birth (`RunLog.original`).
"""

from __future__ import annotations

from functools import cached_property
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, model_validator

from derl.unimal import Genome, body_hash


class Record(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Body(Record):
    """A born body: its place in the tree, its fitness and what lifetime learning measured."""

    id: str
    parent: str | None = None
    birth: int
    fitness: float
    curve_steps: tuple[int, ...] = ()
    curve_returns: tuple[float, ...] = ()
    energy: float = float("nan")
    cost_of_work: float = float("nan")
    """Energy / (mass g reward); NaN when undefined (no forward progress)."""
    mass: float = float("nan")
    mutation: str | None = None
    """The operator that made this body from its parent (None for the initial bodies)."""
    genome: Genome | None = None
    repeat_of: str | None = None
    """The earlier body equal to this one, whose training result it took (None: trained)."""

    @model_validator(mode="after")
    def _curve_aligned(self) -> Body:
        if len(self.curve_steps) != len(self.curve_returns):
            raise ValueError(f"{self.id}: curve steps and returns differ in length")
        return self


class Evaluation(Record):
    """One test-task result of an agent (appendix C), trained from scratch with `seed`."""

    agent: str
    task: str
    seed: int
    steps: int | None = None
    """The budget of env steps it was trained for (the paper reports 5M and 1M; None: unknown)."""
    reward: float
    cost_of_work: float = float("nan")


class Retraining(Record):
    """Appendix D: one of the run's bodies, selected from a surviving lineage, trained again from
    scratch in the run's world with a new `seed` (a `derl study`'s first stage)."""

    agent: str
    seed: int
    steps: int
    fitness: float
    cost_of_work: float = float("nan")


class RunLog(Record):
    """One evolution run: its world, every body in birth order, and its evaluation results."""

    name: str
    world: str
    """The evolution environment (``ft``, ``vt``, ``mvt``): the task of its training jobs."""
    bodies: tuple[Body, ...]
    evaluations: tuple[Evaluation, ...] = ()
    retrained: tuple[Retraining, ...] = ()
    """Its bodies' retrainings with new seeds, where a study selected them (appendix D)."""
    train_steps: int | None = None
    training_seed: int | None = None
    checkpoints: Path | None = None
    """The folder of the bodies' trained policies (``<id>.pt``), where the run was read from a
    directory that has one (a log alone has none)."""
    fingerprint: str | None = None
    """A hash of its births (`derl.evolution.fingerprint`), where it was read from a journal."""
    audited: int = 0
    """Births from two trainings by two trainer identities that agreed (an audit)."""
    quarantined: tuple[str, ...] = ()
    """Trainer identities caught lying by an audit (their unchecked births trained again)."""

    @model_validator(mode="after")
    def _a_tree_in_birth_order(self) -> RunLog:
        seen: set[str] = set()
        for index, body in enumerate(self.bodies):
            if body.birth != index:
                raise ValueError(f"{body.id}: birth {body.birth} at position {index}")
            if body.parent is not None and body.parent not in seen:
                raise ValueError(f"{body.id}: parent {body.parent} is not born before it")
            if body.id in seen:
                raise ValueError(f"{body.id} is born twice")
            seen.add(body.id)
        return self

    @cached_property
    def population(self) -> int:
        """P, the aging window: the initial population is P bodies without a parent."""
        return sum(body.parent is None for body in self.bodies)

    @cached_property
    def fitness(self) -> np.ndarray:
        """Every body's fitness, in birth order."""
        return np.array([body.fitness for body in self.bodies], dtype=float)

    @cached_property
    def cost_of_work(self) -> np.ndarray:
        """Every body's cost of work, in birth order (NaN where undefined)."""
        return np.array([body.cost_of_work for body in self.bodies], dtype=float)

    @cached_property
    def body_keys(self) -> tuple[str, ...]:
        """Each body's identity: that of the earlier body it repeats (it took that body's
        result), else the `body_hash` of its genome, else (no genome) its own id."""
        keys: dict[str, str] = {}
        for body in self.bodies:
            if body.repeat_of in keys:
                keys[body.id] = keys[body.repeat_of]
            else:
                keys[body.id] = body.id if body.genome is None else body_hash(body.genome)
        return tuple(keys[body.id] for body in self.bodies)

    @cached_property
    def original(self) -> np.ndarray:
        """Per body, the index of the run's first body with its identity (its own index for a
        body born new): a repeat counts as its original."""
        first: dict[str, int] = {}
        return np.array([first.setdefault(key, i) for i, key in enumerate(self.body_keys)], int)

    @cached_property
    def distinct(self) -> np.ndarray:
        """Which bodies are born new (not a body born before in the run)."""
        return self.original == np.arange(len(self.bodies))
