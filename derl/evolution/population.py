"""Aging (regularized) tournament evolution as a deterministic state machine, with no bus.

The population is the P most recently born agents, in birth order. The initial P bodies come from
the run's seed; afterwards each tournament draws T members with replacement, the fittest is the
parent (the first drawn among equals), and one mutation of its body is the child. Tournament k
draws from a hash of (seed, k) (`tournament_draws`), so a decision depends only on the state it
was made in: replaying recorded decisions and births rebuilds the same state, and the next
decision is the one the crashed run would have made.

A tournament decides the parent and a mutation seed; `breed(parent body, seed)` makes the child.
Breeding (a mutation and its validity check, a few ms) is deterministic, so it runs wherever the
child is trained, as in the original DERL where every worker mutated its own child. Training is
deterministic within a run, so a child whose body equals one already born (`repeat`, by
`body_hash`: the same body whatever its limb numbering) is born as a repeat with that body's
result instead of being trained again; where it is decided, only the child's first draft (the
first body breeding tries, before the validity check that is most of its cost) is made and
looked up: a draft that is a born body is the child if valid, checked once per born body.
"""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from derl.evolution.config import EvolutionConfig
from derl.unimal import (
    Genome,
    Mutation,
    MutationFailed,
    body_hash,
    check_body,
    is_valid,
    mutate,
    sample_population,
)

MAX_DRAWS = 100


def tournament_draws(
    seed: int, iteration: int, size: int, population: int
) -> tuple[list[int], int]:
    """Tournament `iteration`'s draws: `size` positions in a population of `population`, drawn
    with replacement, and a 63-bit mutation seed. A counter-based generator: 8 bytes of the
    SHAKE-128 digest of (seed, iteration) per draw, a position the 64-bit word modulo
    `population` (a bias under 2**-50). A tenth of what a numpy generator costs to seed, and
    the same draws whatever the numpy version."""
    digest = hashlib.shake_128(f"derl tournament {seed} {iteration}".encode()).digest(
        8 * (size + 1)
    )
    words = struct.unpack(f"<{size + 1}Q", digest)
    return [word % population for word in words[:size]], words[size] >> 1


@dataclass(frozen=True)
class Member:
    """A born agent."""

    agent: str
    fitness: float
    parent: str | None
    birth: int
    repeat_of: str | None = None  # the earlier agent with this body, whose result it took


@dataclass(frozen=True)
class Child:
    """A body to train: an initial one (its genome, no parent) or a tournament's winner to
    breed (`breed(genome of parent, mutation_seed)`; the genome is known once it is born)."""

    name: str
    genome: Genome | None
    parent: str | None = None
    contestants: tuple[str, ...] = ()
    fitness: tuple[float, ...] = ()
    mutation_seed: int | None = None
    iteration: int = -1


def breed(
    parent: Genome, seed: int, check: Callable[[Genome], None] = check_body
) -> tuple[Genome, Mutation]:
    """The child of a tournament: one valid mutation of `parent`, the same for the same seed."""
    rng = np.random.default_rng(seed)
    reason = ""
    for _ in range(MAX_DRAWS):
        try:
            return mutate(parent, rng, check=check)
        except MutationFailed as failure:
            reason = str(failure)
    raise MutationFailed("every drawn operator", MAX_DRAWS, reason)


def _unchecked(genome: Genome) -> None:
    """No validity check (`first_draft`)."""


def first_draft(parent: Genome, seed: int) -> tuple[Genome, Mutation]:
    """The first body `breed(parent, seed)` tries and its mutation, before the validity check
    (MuJoCo's compile, most of breeding's cost): the child itself whenever that body is valid."""
    return breed(parent, seed, check=_unchecked)


class Evolution:
    """Who is born, who may be a parent, and which child comes next."""

    def __init__(self, config: EvolutionConfig, initial: list[Genome] | None = None) -> None:
        """`initial`: the P initial bodies, if already drawn (else drawn from the seed)."""
        self.config = config
        if initial is None:
            initial = sample_population(config.population, np.random.default_rng([config.seed, 0]))
        if len(initial) != config.population:
            raise ValueError(
                f"{len(initial)} initial bodies for a population of {config.population}"
            )
        self.initial = [Child(f"i{k:04d}", genome) for k, genome in enumerate(initial)]
        self.unborn_initial = {child.name for child in self.initial}
        self.genomes: dict[str, Genome] = {c.name: c.genome for c in self.initial}
        self.parents: dict[str, str | None] = {c.name: None for c in self.initial}
        self.seeds: dict[str, int | None] = {c.name: None for c in self.initial}
        self.born: list[Member] = []
        self.fitness: dict[str, float] = {}
        self.given_up: set[str] = set()  # children whose trainings kept failing: never born
        self.bodies: dict[str, str] = {}  # body_hash -> the first agent born with that body
        self.drafts: dict[str, str | None] = {}  # child -> body_hash of its first draft
        self.drafted: dict[str, tuple[Genome, Mutation]] = {}  # that draft, until it is born
        self.valid: dict[str, bool] = {}  # body_hash of a born body -> it passes `check_body`
        self.iterations = 0
        self._best: Member | None = None

    @property
    def population(self) -> list[Member]:
        """The P most recently born agents."""
        return self.born[-self.config.population :]

    @property
    def initial_born(self) -> bool:
        return not self.unborn_initial

    @property
    def settled(self) -> int:
        """Children born or given up."""
        return len(self.born) + len(self.given_up)

    @property
    def complete(self) -> bool:
        """Every child of the run is born or given up."""
        return self.settled >= self.config.total

    def best(self) -> Member | None:
        """The fittest agent born (the first born of equals)."""
        return self._best

    def tournament(self) -> Child:
        """Decide the next child (call `record` with it to make it part of the state)."""
        if not self.initial_born:
            raise RuntimeError("tournaments start once the initial population is born")
        population = self.population
        positions, mutation_seed = tournament_draws(
            self.config.seed, self.iterations, self.config.tournament, len(population)
        )
        drawn = [population[i] for i in positions]
        parent = max(drawn, key=lambda m: m.fitness)
        return Child(
            name=f"c{self.iterations:05d}",
            genome=None,
            parent=parent.agent,
            contestants=tuple(m.agent for m in drawn),
            fitness=tuple(m.fitness for m in drawn),
            mutation_seed=mutation_seed,
            iteration=self.iterations,
        )

    def record(self, child: Child) -> None:
        """A decided tournament becomes a fact (idempotent)."""
        if child.name in self.parents:
            return
        self.parents[child.name] = child.parent
        self.seeds[child.name] = child.mutation_seed
        self.iterations = max(self.iterations, child.iteration + 1)

    def to_train(self, child: str) -> tuple[Genome, int | None]:
        """What a trainer needs for `child`: its body, or its parent's body and the seed to
        breed it with (until it is born)."""
        if child in self.genomes:
            return self.genomes[child], None
        return self.genomes[self.parents[child]], self.seeds[child]

    def give_up(self, child: str) -> None:
        """`child` will never be born (its trainings failed); the run goes on without it."""
        if child in self.parents and child not in self.fitness:
            self.given_up.add(child)
            self.drafted.pop(child, None)
            self.unborn_initial.discard(child)

    def repeat_of(self, genome: Genome) -> str | None:
        """The first agent born with the body `genome` (None: a body not born yet)."""
        return self.bodies.get(body_hash(genome))

    def draft(self, child: str) -> str | None:
        """The `body_hash` of tournament child `child`'s first draft (None: an initial child, or
        one that cannot be bred); the child's own when the draft is valid."""
        if child not in self.drafts:
            parent_body, seed = self.to_train(child)
            key = None
            if seed is not None:
                try:
                    self.drafted[child] = first_draft(parent_body, seed)
                    key = body_hash(self.drafted[child][0])
                except MutationFailed:  # its trainer fails the same way: the child is given up
                    pass
            self.drafts[child] = key
        return self.drafts[child]

    def repeat(self, child: str) -> tuple[str, Genome, Mutation] | None:
        """If tournament child `child` will have a body born already: that agent, the body and
        its mutation. The child's first draft is looked up: one that is a born body and valid is
        the child. A tournament child's body is valid (its trainer bred it with `check_body`);
        an initial body, which may be given by hand, is checked once, at its first lookup
        (`check_body` depends on the body, not on its limbs' numbering). A child whose draft is
        invalid and whose body is born is missed (rare: trained)."""
        key = self.draft(child)
        earlier = self.bodies.get(key)
        if earlier is None or child not in self.drafted:
            return None
        genome, mutation = self.drafted[child]
        if key not in self.valid:
            self.valid[key] = is_valid(genome)
        return (earlier, genome, mutation) if self.valid[key] else None

    def birth(
        self, agent: str, fitness: float, genome: Genome, repeat_of: str | None = None
    ) -> Member | None:
        """`agent` is born with body `genome` and `fitness` (`repeat_of`: taken from that earlier
        agent with the same body); None if it was born already or is unknown."""
        if agent in self.fitness or agent not in self.parents:
            return None
        self.genomes.setdefault(agent, genome)
        drafted = self.drafted.pop(agent, None)  # the draft's hash, if it is the body born
        key = self.drafts[agent] if drafted and drafted[0] == genome else body_hash(genome)
        self.bodies.setdefault(key, agent)
        if self.seeds[agent] is not None:  # bred, so checked, by its trainer (`breed`)
            self.valid[key] = True
        member = Member(agent, fitness, self.parents[agent], len(self.born), repeat_of)
        self.born.append(member)
        if self._best is None or fitness > self._best.fitness:
            self._best = member
        self.fitness[agent] = fitness
        self.unborn_initial.discard(agent)
        return member
