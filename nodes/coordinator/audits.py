"""Audits: a share of the children trained twice, by two trainer identities, to catch a liar.

Training is deterministic (the same body, world, seed and settings give the same bits on one
machine type), so two honest trainings of a child give the same result: fitness, cost of work,
energy, mass, env steps and checkpoint, bit for bit. Which children are audited is drawn from the
run's seed (`audited`), so it is the same in every run of the seed. A child's trials are its
trainings by distinct identities (`<id>.r<n>` is restart n of `<id>`), in the order they came;
`verdict` says what they decide: two that agree make the birth; a disagreement waits for a third
trial, which agrees with one of them (the other identity lied) or with neither (the trainers do
not train alike: different machines or library versions, and nobody can be blamed). This is how
volunteer computing (BOINC) keeps untrusted hosts honest.
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass

from derl.messages import FitnessReport


def audited(seed: int, child: str, share: float) -> bool:
    """Whether `child` of the run seeded `seed` is trained twice (a share `share` of them)."""
    digest = hashlib.sha256(f"derl audit {seed} {child}".encode()).digest()
    return int.from_bytes(digest[:8], "little") < share * 2**64


def identity(node: str) -> str:
    """A worker's identity: ``<id>.r<n>`` is restart n of ``<id>``."""
    return incarnation(node)[0]


def incarnation(node: str) -> tuple[str, int]:
    """A worker's identity and incarnation: ``<id>.r<n>`` is restart n of ``<id>`` (0: itself)."""
    restart = re.fullmatch(r"(.+)\.r(\d+)", node)
    return (node, 0) if restart is None else (restart[1], int(restart[2]))


def result_bits(report: FitnessReport) -> bytes:
    """What two honest trainings of a child share: the result's bits and the checkpoint's
    SHA-256 (`report.checkpoint` holds the digest once journaled: `journaled`)."""
    numbers = struct.pack(
        "<4dq", report.fitness, report.cost_of_work, report.energy, report.mass, report.env_steps
    )
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
