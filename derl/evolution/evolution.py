"""Aging (regularized) tournament evolution as a deterministic state machine, with no bus.

Children are numbered in the order they are bred (`index`): the P initial bodies first, from the
run's seed, then tournament k's child. A tournament draws T members with replacement from a
population, the fittest is the parent (the first drawn among equals), and one mutation of its
body is the child. Which population is the run's `in_flight`, W, the number of children the
evolution keeps in flight (the paper's 288 trainings at once): the child numbered n is bred from
the P latest born of the first n - W children (`pool`), once every one of them is born or given
up (`ready`), whatever order their trainings finished in. So the births depend on the seed
alone, not on how many trainers ran, how fast, or what crashed and resumed. W = 0 is
free-running (the released code's rule, not reproducible): the P most recently born, in the
order they were born, as soon as one is. The cluster timing (`timing: cluster`,
`derl.evolution.timing`) keeps the released code's dynamics instead and stays a function of the
seed: W virtual workers, each breeding a child when its training ends in virtual time (durations
counted from what the training did), from the P bodies that finished last by then; with the
released end (`end: released`), the workers breed while fewer than N bodies finished and the run
keeps the N that finished first. Tournament k draws from a hash of (seed, k)
(`tournament_draws`), so a decision depends only on the state it was made in: replaying recorded
decisions and births rebuilds the same state, and the next decision is the one the crashed run
would have made.

A tournament decides the parent and a mutation seed; `breed(parent body, seed)` makes the child
(a mutation and its full validity check: deterministic, so the same seed gives the same body,
written in its canonical form, `canonical_genome`, so that equal bodies are equal genomes and
train alike). Whoever holds this state breeds the child (`body`) before it is trained, so every
body is decided here, recorded once decided (`decided`: a journal that carries it gives it back),
and a trainer trains the body it is given. Training is deterministic, so a child whose body equals
one already born (`repeat`, by `body_hash`) is born as a repeat with that body's result instead of
being trained again; where children inherit their parent's weights (`inherit: parent`), only one
whose parent's training was the same too (`body_key`).
"""

from __future__ import annotations

import bisect
import hashlib
import struct
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from derl.evolution.config import EvolutionConfig
from derl.evolution.member import Member
from derl.evolution.selection import Draws, make_selection, select
from derl.evolution.timing import ClusterClock
from derl.unimal import (
    Genome,
    Mutation,
    MutationFailed,
    body_hash,
    canonical_genome,
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


def tournament_child(iteration: int) -> str:
    """The name of tournament `iteration`'s child."""
    return f"c{iteration:05d}"


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


def breed(
    parent: Genome,
    seed: int,
    released_delete: bool = True,
    weights: Mapping[str, float] | None = None,
) -> tuple[Genome, Mutation]:
    """The child of a tournament: one valid mutation of `parent`, the same for the same seed
    (each operator tries up to 50 times, and up to `MAX_DRAWS` operators are drawn), in its
    canonical form (the limb ids in the mutation's detail are the parent's); `released_delete`
    and `weights` (the operators' shares, None: the paper's uniform choice): as
    `derl.unimal.mutate`'s."""
    rng = np.random.default_rng(seed)
    reason = ""
    for _ in range(MAX_DRAWS):
        try:
            child, mutation = mutate(parent, rng, released_delete=released_delete, weights=weights)
            return canonical_genome(child), mutation
        except MutationFailed as failure:
            reason = str(failure)
    raise MutationFailed("every drawn operator", MAX_DRAWS, reason)


class Evolution:
    """Who is born, who may be a parent, and which child comes next."""

    def __init__(self, config: EvolutionConfig, initial: list[Genome] | None = None) -> None:
        """`initial`: the P initial bodies, if already drawn (else drawn from the seed)."""
        self.config = config
        self.selection = make_selection(config.selection, config.selection_options)
        if initial is None:
            initial = sample_population(config.population, np.random.default_rng([config.seed, 0]))
        if len(initial) != config.population:
            raise ValueError(
                f"{len(initial)} initial bodies for a population of {config.population}"
            )
        genomes = [canonical_genome(genome) for genome in initial]
        self.initial = [Child(f"i{k:04d}", genome) for k, genome in enumerate(genomes)]
        # every child's body once decided (an initial one from the start), and its mutation
        self.genomes: dict[str, Genome] = {
            c.name: genome for c, genome in zip(self.initial, genomes, strict=True)
        }
        self.mutations: dict[str, Mutation | None] = {c.name: None for c in self.initial}
        self.parents: dict[str, str | None] = {c.name: None for c in self.initial}
        self.seeds: dict[str, int | None] = {c.name: None for c in self.initial}
        self.born: list[Member] = []
        self.births_made = 0  # births ever (an undone one's number is not given again)
        self.fitness: dict[str, float] = {}
        self.given_up: set[str] = set()  # children never born (not bred, or trainings failed)
        self.bodies: dict[str, str] = {}  # body_key -> the first agent born with it
        self.hashes: dict[str, str] = {}  # child -> its body_key (computed once)
        self.iterations = 0
        self._best: Member | None = None
        self.index: dict[str, int] = {c.name: k for k, c in enumerate(self.initial)}
        self.born_indices: list[int] = []  # the born children's numbers, ascending
        self.by_index: dict[int, Member] = {}  # a born child's number -> it
        self.settled_indices: set[int] = set()  # numbers of children born or given up
        self.prefix = 0  # the first `prefix` children are all born or given up
        self.clock: ClusterClock | None = None  # the cluster timing's (`derl.evolution.timing`)
        self.closed = False  # the released end: N bodies finished, no child is bred any more
        self.dropped: set[str] | None = None  # the released end: the children dropped
        if config.timing == "cluster":
            self.steps = config.training_ppo().total_steps  # every training's env steps
            least = config.training_time.least(self.steps)
            self.clock = ClusterClock(config.in_flight, len(self.initial), config.population, least)

    @property
    def population(self) -> list[Member]:
        """The P latest born agents: in child order (in the order they were born when
        free-running, of their virtual finishes in the cluster timing)."""
        if self.clock is not None:
            return [self.by_index[k] for _, k in self.clock.finished[-self.config.population :]]
        if not self.config.in_flight:
            return self.born[-self.config.population :]
        latest = self.born_indices[-self.config.population :]
        return [self.by_index[k] for k in latest]

    def pool(self) -> list[Member] | None:
        """The population the next tournament draws from, None while it is not known yet: the P
        latest born of the first n - W children, n the next child's number, once each of them is
        born or given up (should none of them be born: of the first children up to the first
        born one). Free-running (W = 0): the P most recently born, once one is. The cluster
        timing: the P that finished last in virtual time when the next child is bred
        (`ClusterClock.breeding`); with the released end, none once N bodies finished by then
        (`closed`)."""
        config = self.config
        if self.clock is not None:
            breeding = None if self.closed else self.clock.breeding(self.iterations)
            if breeding is None:
                return None
            if config.end == "released" and breeding[2] >= config.total:
                self.closed = True  # N bodies finished: the released code's workers stop
                return None
            return [self.by_index[k] for k in breeding[1]]
        if not config.in_flight:
            return self.born[-config.population :] or None
        if not self.born_indices or self.born_indices[0] >= self.prefix:
            return None  # no child is born among the settled ones yet
        first = max(len(self.initial) + self.iterations - config.in_flight,
                    self.born_indices[0] + 1)  # fmt: skip
        if self.prefix < first:
            return None
        end = bisect.bisect_left(self.born_indices, first)
        latest = self.born_indices[max(0, end - config.population) : end]
        return [self.by_index[k] for k in latest]

    @property
    def settled(self) -> int:
        """Children born or given up."""
        return len(self.born) + len(self.given_up)

    @property
    def complete(self) -> bool:
        """Every child of the run is born or given up (with the released end: what was in
        flight at the N-th finish is dropped, `drop`)."""
        if self.config.end == "released":
            return self.dropped is not None
        return self.settled >= self.config.total

    def released_end(self) -> list[str] | None:
        """With the released end (`end: released`), once it is known: the children bred that
        are not among the N born that finished first in virtual time (in flight when the N-th
        finished, or trained past it), to `drop`; None before (or with the other end, or once
        dropped)."""
        if self.config.end != "released" or self.dropped is not None or self.clock is None:
            return None
        if not self.closed:
            self.pool()  # closes it if N bodies finished by the next breeding
        if not self.closed or self.clock.nth_finish(self.config.total) is None:
            return None
        kept = {k for _, k in self.clock.finished[: self.config.total]}
        bred = (c for c in self.parents if self.index[c] not in kept and c not in self.given_up)
        return sorted(bred, key=self.index.__getitem__)

    def drop(self, children: list[str]) -> None:
        """The released end: `children` (`released_end`) never joined the population (none is
        a parent: each finished after every breeding); a born one's birth does not count."""
        gone = set(children)
        self.dropped = gone
        self.born = [m for m in self.born if m.agent not in gone]
        for child in gone:
            self.fitness.pop(child, None)
        indices = {self.index[c] for c in gone if c in self.index}
        self.by_index = {k: m for k, m in self.by_index.items() if k not in indices}
        self.born_indices = sorted(self.by_index)
        if self.clock is not None:
            self.clock.finished = [f for f in self.clock.finished if f[1] not in indices]
        self._best = self._fittest()

    def best(self) -> Member | None:
        """The fittest agent born (the first in child order of equals)."""
        return self._best

    def tournament(self) -> Child | None:
        """Decide the next child from its `pool` (None while that is not known yet) by the run's
        selection scheme (`derl.evolution.selection`; `PluginError` if a plugin's chooses outside
        the pool); call `record` with it to make it part of the state."""
        population = self.pool()
        if population is None:
            return None
        config = self.config
        positions, mutation_seed = tournament_draws(
            config.seed, self.iterations, config.tournament, len(population)
        )
        draws = Draws(tuple(positions), config.seed, self.iterations)
        chosen = select(config.selection, self.selection, population, draws)
        return Child(
            name=tournament_child(self.iterations),
            genome=None,
            parent=chosen.parent.agent,
            contestants=tuple(m.agent for m in chosen.contestants),
            fitness=tuple(m.fitness for m in chosen.contestants),
            mutation_seed=mutation_seed,
            iteration=self.iterations,
        )

    def record(self, child: Child) -> None:
        """A decided tournament becomes a fact (idempotent)."""
        if child.name in self.parents:
            return
        self.parents[child.name] = child.parent
        self.seeds[child.name] = child.mutation_seed
        self.index[child.name] = len(self.initial) + child.iteration
        self.iterations = max(self.iterations, child.iteration + 1)

    def body(self, child: str) -> tuple[Genome, Mutation | None]:
        """`child`'s body and the mutation that made it (None: an initial body): a tournament's
        child is bred from its parent's body the first time it is asked for (a few ms: the
        validity check compiles the body; `MutationFailed` if no valid child comes of it)."""
        if child not in self.genomes:
            seed, parent = self.seeds[child], self.parents[child]
            assert seed is not None and parent is not None, child
            config = self.config
            bred = breed(self.genomes[parent], seed, config.released_delete_limb, config.mutations)
            self.decided(child, *bred)
        return self.genomes[child], self.mutations[child]

    def decided(self, child: str, genome: Genome, mutation: Mutation | None) -> None:
        """`child`'s body is `genome` (made by `mutation`): a fact, as its job records it."""
        if child not in self.genomes:
            self.genomes[child] = genome
            self.mutations[child] = mutation

    def body_key(self, child: str) -> str:
        """What `child`'s training is a function of (its body decided before): the `body_hash`
        of its body, and where the run inherits (`inherit: parent`) its parent's key too (it
        starts from the parent's trained weights)."""
        key = self.hashes.get(child)
        if key is None:
            key = body_hash(self.genomes[child])
            parent = self.parents[child]
            if self.config.inherit == "parent" and parent is not None:
                key = hashlib.sha256(f"{key} {self.body_key(parent)}".encode()).hexdigest()
            self.hashes[child] = key
        return key

    def give_up(self, child: str) -> None:
        """`child` will never be born (it could not be bred, or its trainings failed); the run
        goes on without it."""
        if child in self.parents and child not in self.fitness:
            self.given_up.add(child)
            self._settled(self.index[child])
            if self.clock is not None:  # its worker was busy for the least time
                self.clock.done(self.index[child], self.clock.least, born=False)

    def skip(self, iteration: int) -> None:
        """Tournament `iteration` is not in the state (lost with a damaged segment): its name
        is never given to another child (`settle_skipped` then counts it as given up)."""
        self.iterations = max(self.iterations, iteration + 1)

    def settle_skipped(self) -> None:
        """Every tournament before the next one that the state lacks (lost with a damaged
        segment) counts as given up, so later ones do not wait for it."""
        for iteration in range(self.iterations):
            if tournament_child(iteration) not in self.parents:
                self._settled(len(self.initial) + iteration)
                if self.clock is not None:
                    self.clock.done(len(self.initial) + iteration, self.clock.least, born=False)

    def _settled(self, index: int) -> None:
        """The child numbered `index` is born or given up."""
        self.settled_indices.add(index)
        while self.prefix in self.settled_indices:
            self.prefix += 1

    def correct(
        self,
        agent: str,
        fitness: float,
        cost_of_work: float = float("nan"),
        work: tuple[int, int] | None = None,
    ) -> None:
        """`agent` (born) and its repeats have `fitness` and `cost_of_work`, not what they were
        born with (it was trained again: the first result was a lie); `work`, if said: its
        training's episodes and constraint rows (the cluster timing's duration)."""
        if agent not in self.fitness:
            return
        for k, member in enumerate(self.born):
            if agent in (member.agent, member.repeat_of):
                self.born[k] = self.by_index[self.index[member.agent]] = replace(
                    member, fitness=fitness, cost_of_work=cost_of_work
                )
                self.fitness[member.agent] = fitness
        self._best = self._fittest()
        if self.clock is not None and work is not None:
            duration = self.config.training_time.duration(self.steps, *work)
            self._new_clock({self.index[agent]: duration})

    def decided_from(self, iteration: int) -> list[str]:
        """The children of the tournaments from `iteration` on that are decided, in child order."""
        first = len(self.initial) + iteration
        return sorted((c for c, k in self.index.items() if k >= first), key=self.index.__getitem__)

    def undo(self, iteration: int) -> list[str]:
        """Every tournament from `iteration` on is void (decided while a lie was in the
        population): its child is forgotten, born or not, and the next tournament is
        `iteration` again, decided from the state the earlier ones left. The children
        forgotten, in child order; a born one that was a repeat of one of them is its own."""
        first = len(self.initial) + iteration
        void = self.decided_from(iteration)
        for child in void:
            self.genomes.pop(child, None)
            self.mutations.pop(child, None)
            self.parents.pop(child, None)
            self.seeds.pop(child, None)
            self.fitness.pop(child, None)
            self.hashes.pop(child, None)
            self.given_up.discard(child)
            del self.index[child]
        gone = set(void)
        self.born = [
            replace(m, repeat_of=None) if m.repeat_of in gone else m
            for m in self.born
            if m.agent not in gone
        ]
        self.by_index = {self.index[m.agent]: m for m in self.born}
        self.born_indices = sorted(self.by_index)
        self.settled_indices = {k for k in self.settled_indices if k < first}
        self.prefix = min(self.prefix, first)
        self.iterations = iteration
        self.closed = False
        self.bodies = {}
        for member in self.born:
            self.bodies.setdefault(self.body_key(member.agent), member.agent)
        self._best = self._fittest()
        if self.clock is not None:
            self._new_clock({}, before=first)
        return void

    def _fittest(self) -> Member | None:
        """The fittest born agent, the first in child order of equals (`best`)."""
        if not self.born:
            return None
        return max(self.born, key=lambda m: (m.fitness, -self.index[m.agent]))

    def _new_clock(self, durations: dict[int, int], before: int | None = None) -> None:
        """The cluster clock again from its children's durations (`durations` replacing some;
        only children numbered below `before`, if given): a duration it knew changed, or
        children were forgotten."""
        old = self.clock
        assert old is not None
        clock = ClusterClock(self.config.in_flight, len(self.initial), self.config.population,
                             old.least)  # fmt: skip
        for child, duration in sorted({**old.duration, **durations}.items()):
            if before is None or child < before:
                clock.done(child, duration, born=child in old.born)
        self.clock = clock

    def repeat_of(self, genome: Genome) -> str | None:
        """The first agent born with the body `genome` (None: a body not born yet)."""
        return self.bodies.get(body_hash(genome))

    def repeat(self, child: str) -> str | None:
        """The agent born already with `child`'s body (decided before), if another."""
        earlier = self.bodies.get(self.body_key(child))
        return None if earlier == child else earlier

    def birth(
        self,
        agent: str,
        fitness: float,
        genome: Genome,
        repeat_of: str | None = None,
        work: tuple[int, int] = (0, 0),
        cost_of_work: float = float("nan"),
    ) -> Member | None:
        """`agent` is born with body `genome` and `fitness` (`repeat_of`: taken from that earlier
        agent with the same body); `work`: its training's episodes and constraint rows (the
        cluster timing's duration); None if it was born already or is unknown."""
        if agent in self.fitness or agent not in self.parents:
            return None
        self.genomes.setdefault(agent, genome)
        self.bodies.setdefault(self.body_key(agent), agent)
        member = Member(
            agent, fitness, self.parents[agent], self.births_made, repeat_of, cost_of_work
        )
        self.births_made += 1
        self.born.append(member)
        index = self.index[agent]
        bisect.insort(self.born_indices, index)
        self.by_index[index] = member
        self._settled(index)
        if self.clock is not None:
            duration = self.config.training_time.duration(self.steps, *work)
            self.clock.done(index, duration, born=True)
        if self._best is None or (fitness, -index) > (
            self._best.fitness,
            -self.index[self._best.agent],
        ):
            self._best = member
        self.fitness[agent] = fitness
        return member
