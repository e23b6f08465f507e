"""Audits: children trained twice, by two trainer identities, to catch a liar before its lies count.

Training is deterministic (the same body, world, seed and settings give the same bits on one
machine type), so two honest trainings of a child give the same result: fitness, cost of work,
energy, mass, env steps and checkpoint, bit for bit. Which children are audited is drawn from the
run's seed (`audited`), so it is the same in every run of the seed. A child's trials are its
trainings by distinct identities (`<id>.r<n>` is restart n of `<id>`), in the order they came;
`verdict` says what they decide: two that agree make the birth; a disagreement waits for a third
trial, which agrees with one of them (the other identity lied) or with neither (the trainers do
not train alike: different machines or library versions, and nobody can be blamed). This is how
volunteer computing (BOINC) keeps untrusted hosts honest.

Which children are audited is decided at a child's first report (`Rules.audits`), from the run's
seed and the journal's facts alone, so a restarted coordinator decides the same: the profile's
share of every child (`audit`), every report of an identity until `audit_first` of its results
agreed with another identity's (BOINC's adaptive replication: a new host's results are always
checked; a disagreement it was part of makes it new again), then a share of its reports that falls
with its record (`Record.share`), and a child whose reported fitness would rank among the best
`audit_top` of the population (a likely parent: the fitness that shapes the run). A liar that
lies on every report is so caught at its first, before any of its reports is born from.
"""

from __future__ import annotations

import hashlib
import re
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from derl.evolution import EvolutionConfig, Member
from derl.messages import FitnessReport


def audited(seed: int, child: str, share: float) -> bool:
    """Whether `child` of the run seeded `seed` is trained twice (a share `share` of them)."""
    digest = hashlib.sha256(f"derl audit {seed} {child}".encode()).digest()
    return int.from_bytes(digest[:8], "little") < share * 2**64


@dataclass
class Record:
    """A trainer identity's record: its results that agreed with another identity's, and its
    reports taken, since the last disagreement it was part of."""

    agreed: int = 0
    reports: int = 0

    def share(self, first: int) -> float:
        """The share of its reports audited: all until `first` agreed, then (first / (n + 1))²,
        n its reports taken."""
        if self.agreed < first:
            return 1.0
        return (first / (self.reports + 1)) ** 2


@dataclass(frozen=True)
class Rules:
    """Which children a run audits (see the module): its profile's `audit`, `audit_first` and
    `audit_top` (all off where `audit` is 0)."""

    seed: int
    share: float
    first: int
    top: float

    @classmethod
    def of(cls, config: EvolutionConfig) -> Rules:
        return cls(config.seed, config.audit, config.audit_first, config.audit_top)

    def drawn(self, child: str) -> bool:
        """Whether `child` is among the profile's share of audited children."""
        return audited(self.seed, child, self.share)

    def audits(
        self,
        child: str,
        node: str,
        fitness: float,
        record: Record,
        population: Callable[[], Sequence[Member]],
    ) -> bool:
        """Whether the first report of `child`, by `node` with `fitness`, makes it audited: it is
        drawn, or the record of `node`'s identity (`Record.share`) or the fitness's rank in the
        `population()` asks for it."""
        if self.share <= 0:
            return False
        if self.drawn(child):
            return True
        draw = f"{child} {identity(node)}"
        if record.agreed < self.first or audited(self.seed, draw, record.share(self.first)):
            return True
        if self.top <= 0:
            return False
        members = population()
        better = sum(member.fitness > fitness for member in members)
        return better < self.top * len(members)


def identity(node: str) -> str:
    """A worker's identity: ``<id>.r<n>`` is restart n of ``<id>``."""
    return incarnation(node)[0]


def incarnation(node: str) -> tuple[str, int]:
    """A worker's identity and incarnation: ``<id>.r<n>`` is restart n of ``<id>`` (0: itself)."""
    restart = re.fullmatch(r"(.+)\.r(\d+)", node)
    return (node, 0) if restart is None else (restart[1], int(restart[2]))


def result_bits(report: FitnessReport) -> bytes:
    """What two honest trainings of a child share: the result's bits (with its episodes and
    constraint rows: the cluster timing's duration) and the checkpoint's SHA-256
    (`report.checkpoint` holds the digest once journaled: `journaled`)."""
    numbers = struct.pack(
        "<4d3q", report.fitness, report.cost_of_work, report.energy, report.mass,
        report.env_steps, report.episodes, report.constraint_rows,
    )  # fmt: skip
    return numbers + report.checkpoint


def journaled(report: FitnessReport) -> FitnessReport:
    """`report` as the journal keeps it: its checkpoint (in its file) replaced by its SHA-256."""
    return report.model_copy(update={"checkpoint": hashlib.sha256(report.checkpoint).digest()})


@dataclass(frozen=True)
class Verdict:
    """What a child's trials decide: the report it is born from, the identity that lied (if one
    did), and whether the trials disagreed with no majority (`undecided`)."""

    born_from: FitnessReport
    liar: str | None = None
    undecided: bool = False


def trials(reports: list[FitnessReport]) -> list[FitnessReport]:
    """The reports that count: the first of each identity, in the order they came."""
    seen: set[str] = set()
    first = []
    for report in reports:
        if identity(report.node) not in seen:
            seen.add(identity(report.node))
            first.append(report)
    return first


def verdict(reports: list[FitnessReport]) -> Verdict | None:
    """What a child's journaled reports decide (None: another trial is needed)."""
    counted = trials(reports)
    if len(counted) < 2:
        return None
    first, second = counted[:2]
    if result_bits(first) == result_bits(second):
        return Verdict(first)
    if len(counted) < 3:
        return None
    third = counted[2]
    if result_bits(third) == result_bits(first):
        return Verdict(first, liar=identity(second.node))
    if result_bits(third) == result_bits(second):
        return Verdict(second, liar=identity(first.node))
    return Verdict(third, undecided=True)
