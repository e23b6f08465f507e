"""The family tree of a run: founders, generations, descendants, lineages, beneficial mutations,
the aging population over time and its lineage abundances (the paper's fig. 2b-h).

A lineage is everything descended from one founder (a body of the initial population, generation
0); a body's generation is its depth below its founder. The population after t births is the P
most recent of them, so a lineage survives when it has a member among the last P bodies born.

The tree, the population and the lineages' shares hold every birth, repeats included (a repeat
takes a place in the population like any child). A mutation is counted once: a birth that turns
a parent body into a child body (each as its original, `RunLog.original`) that an earlier birth
already made is the same mutation found again, not another beneficial one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derl.analysis.records import Record, RunLog

TOPOLOGY_CHANGES = frozenset({"grow_limb", "delete_limb"})


@dataclass(frozen=True)
class Tree:
    """Index arrays over a run's bodies in birth order (-1 where there is no parent)."""

    parent: np.ndarray
    founder: np.ndarray
    generation: np.ndarray
    descendants: np.ndarray
    """All bodies below each one, at any depth."""

    @classmethod
    def of(cls, run: RunLog) -> Tree:
        index = {body.id: i for i, body in enumerate(run.bodies)}
        n = len(run.bodies)
        parent = np.array([-1 if b.parent is None else index[b.parent] for b in run.bodies], int)
        founder, generation = np.arange(n), np.zeros(n, int)
        for i in range(n):  # parents are born first
            if parent[i] >= 0:
                founder[i], generation[i] = founder[parent[i]], generation[parent[i]] + 1
        descendants = np.zeros(n, int)
        for i in range(n - 1, -1, -1):
            if parent[i] >= 0:
                descendants[parent[i]] += descendants[i] + 1
        return cls(parent, founder, generation, descendants)

    def ancestry(self, body: int) -> list[int]:
        """The bodies from the founder down to `body`, one per generation."""
        chain = [body]
        while self.parent[chain[-1]] >= 0:
            chain.append(int(self.parent[chain[-1]]))
        return chain[::-1]

    def preorder(self) -> list[int]:
        """Every body, each lineage's subtree contiguous, children in birth order."""
        children: list[list[int]] = [[] for _ in self.parent]
        for child, parent in enumerate(self.parent):
            if parent >= 0:
                children[parent].append(child)
        order: list[int] = []
        stack = [int(i) for i in np.flatnonzero(self.parent < 0)[::-1]]
        while stack:
            body = stack.pop()
            order.append(body)
            stack.extend(reversed(children[body]))
        return order


def window(t: int, population: int) -> slice:
    """The population after t births: the P most recently born bodies."""
    return slice(max(0, t - population), t)


def time_grid(run: RunLog, points: int) -> np.ndarray:
    """Birth counts to evaluate the population at: from the initial population to the end."""
    return shared_grid([run], points)


def shared_grid(runs: list[RunLog], points: int) -> np.ndarray:
    """Birth counts at which every one of `runs` has a whole population: from the largest initial
    population to the end of the shortest run."""
    end = min(len(run.bodies) for run in runs)
    start = min(max(run.population for run in runs), end)
    return np.unique(np.linspace(start, end, min(points, end - start + 1)).round().astype(int))


def fitness_gain(run: RunLog, tree: Tree) -> np.ndarray:
    """Child minus parent fitness of every mutation (NaN for the initial bodies)."""
    gain = np.full(len(run.bodies), np.nan)
    child = tree.parent >= 0
    gain[child] = run.fitness[child] - run.fitness[tree.parent[child]]
    return gain


def new_mutations(run: RunLog, tree: Tree) -> np.ndarray:
    """Which births are a mutation made for the first time: from a parent body to a child body
    (each as its original) that no earlier birth made."""
    made: set[tuple[int, int]] = set()
    flags = np.zeros(len(run.bodies), bool)
    for i in np.flatnonzero(tree.parent >= 0):
        pair = (int(run.original[tree.parent[i]]), int(run.original[i]))
        flags[i] = pair not in made
        made.add(pair)
    return flags


def beneficial(run: RunLog, tree: Tree, threshold: float) -> np.ndarray:
    """Which births are a beneficial mutation: made for the first time (`new_mutations`), with
    a gain over the parent of >= `threshold`."""
    return (fitness_gain(run, tree) >= threshold) & new_mutations(run, tree)  # NaN: False


def final_members(run: RunLog, tree: Tree) -> dict[int, int]:
    """Members in the final population by founder, for the surviving lineages, largest first
    (earlier founder first among equals)."""
    founders = tree.founder[window(len(run.bodies), run.population)]
    values, counts = np.unique(founders, return_counts=True)
    order = np.lexsort((values, -counts))
    return {int(values[k]): int(counts[k]) for k in order}


class Lineage(Record):
    """One founder's lineage (a row of lineages.csv)."""

    run: str
    founder: str
    founder_fitness: float
    founder_rank: int
    """Rank of the founder's fitness in the initial population (1 = fittest)."""
    bodies: int
    """Births in the lineage, repeats included."""
    distinct_bodies: int
    """Its bodies counted once (repeats as their original)."""
    final_members: int
    final_abundance: float
    """Share of the final population that belongs to this lineage."""
    surviving: bool
    beneficial_mutations: int
    max_generation: int
    best_agent: str
    best_fitness: float


def lineages(run: RunLog, tree: Tree, threshold: float) -> list[Lineage]:
    """Every lineage of the run, by final abundance (largest first), then founder birth."""
    founders = np.flatnonzero(tree.parent < 0)
    final = final_members(run, tree)
    size = sum(final.values())
    gains = beneficial(run, tree, threshold)
    order = np.argsort(-run.fitness[founders], kind="stable")
    rank = {int(founders[k]): position + 1 for position, k in enumerate(order)}
    rows = []
    for f in founders:
        members = np.flatnonzero(tree.founder == f)
        best = int(members[np.argmax(run.fitness[members])])
        count = final.get(int(f), 0)
        rows.append(
            Lineage(
                run=run.name,
                founder=run.bodies[f].id,
                founder_fitness=float(run.fitness[f]),
                founder_rank=rank[int(f)],
                bodies=members.size,
                distinct_bodies=int(run.distinct[members].sum()),
                final_members=count,
                final_abundance=count / size,
                surviving=count > 0,
                beneficial_mutations=int(gains[members].sum()),
                max_generation=int(tree.generation[members].max()),
                best_agent=run.bodies[best].id,
                best_fitness=float(run.fitness[best]),
            )
        )
    return sorted(rows, key=lambda r: -r.final_members)


@dataclass(frozen=True)
class Muller:
    """Abundance over time of the lineages with the largest final abundance (fig. 2f-h)."""

    times: np.ndarray
    founders: list[str]
    abundance: np.ndarray
    """(times, lineages): share of the population after t births; rows sum to <= 1."""
    fitness: np.ndarray
    """(times, lineages): mean fitness of the lineage's members in that population (NaN: none)."""
    stars: list[tuple[int, int, str]]
    """(birth, lineage column, body) of topology changes with many descendants."""


def muller(
    run: RunLog,
    tree: Tree,
    rows: list[Lineage],
    times: np.ndarray,
    count: int,
    star_descendants: int,
) -> Muller:
    """The `count` largest surviving lineages of `rows` (as `lineages` sorts them) at `times`."""
    index = {body.id: i for i, body in enumerate(run.bodies)}
    surviving = [row.founder for row in rows if row.surviving][:count]
    columns = [index[f] for f in surviving]
    abundance = np.zeros((times.size, len(columns)))
    fitness = np.full((times.size, len(columns)), np.nan)
    for row, t in enumerate(times):
        span = window(int(t), run.population)
        members, values = tree.founder[span], run.fitness[span]
        for column, f in enumerate(columns):
            mine = members == f
            abundance[row, column] = mine.sum() / max(1, members.size)
            if mine.any():
                fitness[row, column] = values[mine].mean()
    stars = [
        (i, columns.index(int(tree.founder[i])), body.id)
        for i, body in enumerate(run.bodies)
        if body.mutation in TOPOLOGY_CHANGES
        and tree.descendants[i] > star_descendants
        and int(tree.founder[i]) in columns
    ]
    return Muller(times, surviving, abundance, fitness, stars)
