"""Aging (regularized) tournament evolution as a deterministic state machine, with no bus.

The population is the P most recently born agents, in birth order. The initial P bodies come from
the run's seed; afterwards each tournament draws T members with replacement from the births so
far (fewer than P while initial bodies are still training), the fittest is the parent (the first
drawn among equals), and one mutation of its body is the child. Tournament k draws from a hash of
(seed, k) (`tournament_draws`), so a decision depends only on the state it was made in: replaying
recorded decisions and births rebuilds the same state, and the next decision is the one the
crashed run would have made.

A tournament decides the parent and a mutation seed; `breed(parent body, seed)` makes the child
(a mutation and its full validity check: deterministic, so the same seed gives the same body).
Whoever holds this state breeds the child (`body`) before it is trained, so every body is
decided here, recorded once decided (`decided`: a journal that carries it gives it back), and a
trainer trains the body it is given. Training is deterministic within a run, so a child whose
body equals one already born (`repeat`, by `body_hash`: the same body whatever its limb
numbering) is born as a repeat with that body's result instead of being trained again.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass

import numpy as np

from derl.evolution.config import EvolutionConfig
from derl.unimal import (
    Genome,
    Mutation,
    MutationFailed,
    body_hash,
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
    """A body to train: an initial one (its genome, no parent) or a tournament's decision, the
    child of `parent` to breed with `mutation_seed` (`Evolution.body`)."""

    name: str
    genome: Genome | None
    parent: str | None = None
    contestants: tuple[str, ...] = ()
    fitness: tuple[float, ...] = ()
    mutation_seed: int | None = None
    iteration: int = -1


def breed(parent: Genome, seed: int) -> tuple[Genome, Mutation]:
    """The child of a tournament: one valid mutation of `parent`, the same for the same seed
    (each operator tries up to 50 times, and up to `MAX_DRAWS` operators are drawn)."""
    rng = np.random.default_rng(seed)
    reason = ""
    for _ in range(MAX_DRAWS):
        try:
            return mutate(parent, rng)
        except MutationFailed as failure:
            reason = str(failure)
    raise MutationFailed("every drawn operator", MAX_DRAWS, reason)


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
        # every child's body once decided (an initial one from the start), and its mutation
        self.genomes: dict[str, Genome] = {c.name: c.genome for c in self.initial}
        self.mutations: dict[str, Mutation | None] = {c.name: None for c in self.initial}
        self.parents: dict[str, str | None] = {c.name: None for c in self.initial}
        self.seeds: dict[str, int | None] = {c.name: None for c in self.initial}
        self.born: list[Member] = []
        self.fitness: dict[str, float] = {}
        self.given_up: set[str] = set()  # children never born (not bred, or trainings failed)
        self.bodies: dict[str, str] = {}  # body_hash -> the first agent born with that body
        self.hashes: dict[str, str] = {}  # child -> body_hash of its body (computed once)
        self.iterations = 0
        self._best: Member | None = None

    @property
    def population(self) -> list[Member]:
        """The P most recently born agents."""
        return self.born[-self.config.population :]

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
        """Decide the next child from the births so far (call `record` with it to make it part
        of the state)."""
        population = self.population
        if not population:
            raise RuntimeError("a tournament needs an agent born")
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

    def body(self, child: str) -> tuple[Genome, Mutation | None]:
        """`child`'s body and the mutation that made it (None: an initial body): a tournament's
        child is bred from its parent's body the first time it is asked for (a few ms: the
        validity check compiles the body; `MutationFailed` if no valid child comes of it)."""
        if child not in self.genomes:
            seed = self.seeds[child]
            assert seed is not None, child
            self.decided(child, *breed(self.genomes[self.parents[child]], seed))
        return self.genomes[child], self.mutations[child]

    def decided(self, child: str, genome: Genome, mutation: Mutation | None) -> None:
        """`child`'s body is `genome` (made by `mutation`): a fact, as its job records it."""
        if child not in self.genomes:
            self.genomes[child] = genome
            self.mutations[child] = mutation

    def body_key(self, child: str) -> str:
        """The `body_hash` of `child`'s body (decided before)."""
        key = self.hashes.get(child)
        if key is None:
            key = self.hashes[child] = body_hash(self.genomes[child])
        return key

    def give_up(self, child: str) -> None:
        """`child` will never be born (it could not be bred, or its trainings failed); the run
        goes on without it."""
        if child in self.parents and child not in self.fitness:
            self.given_up.add(child)

    def repeat_of(self, genome: Genome) -> str | None:
        """The first agent born with the body `genome` (None: a body not born yet)."""
        return self.bodies.get(body_hash(genome))

    def repeat(self, child: str) -> str | None:
        """The agent born already with `child`'s body (decided before), if another."""
        earlier = self.bodies.get(self.body_key(child))
        return None if earlier == child else earlier

    def birth(
        self, agent: str, fitness: float, genome: Genome, repeat_of: str | None = None
    ) -> Member | None:
        """`agent` is born with body `genome` and `fitness` (`repeat_of`: taken from that earlier
        agent with the same body); None if it was born already or is unknown."""
        if agent in self.fitness or agent not in self.parents:
            return None
        self.genomes.setdefault(agent, genome)
        self.bodies.setdefault(self.body_key(agent), agent)
        member = Member(agent, fitness, self.parents[agent], len(self.born), repeat_of)
        self.born.append(member)
        if self._best is None or fitness > self._best.fitness:
            self._best = member
        self.fitness[agent] = fitness
        return member
