"""The crash checker (`derl.nodes.testing.crash_check`, which tests/test_crash.py and
bench/crash.py run on every crash state of a recorded run) rejects run directories that break its
invariants: a child born twice, an acknowledged birth whose checkpoint file is missing or another
child's, a best body's folder without its checkpoint, a journal that lost a job a trainer had
received and a birth it had acknowledged. Each is a whole run of the crash profile, made by the
coordinator's own code in this process (`check` on an empty folder: a real journal, real
checkpoint files), then broken as a faulty coordinator would leave it: messages written with the
real journal writer, files removed or overwritten. The checker accepts the whole run."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest

from derl.messages import Ack, Birth, MessageBase, TrainJob
from derl.nodes.journal.segments import Journal, replay
from derl.nodes.testing.crash import NODES
from derl.nodes.testing.crash_check import check, journal_holds
from derl.nodes.testing.disk import Knowledge


@dataclass(frozen=True)
class Whole:
    """A finished run of the crash profile and what its trainers were told."""

    folder: Path
    journal: list[MessageBase]
    knowledge: Knowledge  # every job received, every birth acknowledged
    jobs: dict[str, TrainJob]

    def copy(self, to: Path) -> Path:
        shutil.copytree(self.folder, to)
        return to

    def last_birth(self) -> Birth:
        return [m for m in self.journal if isinstance(m, Birth)][-1]


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory) -> Whole:
    folder = tmp_path_factory.mktemp("crash-check") / "run"
    idle = tuple((node, None, True) for node in NODES)  # no job held: each asks for work
    assert check(folder, Knowledge(idle, frozenset(), ()), {}) == []  # the run, start to end
    journal = list(replay(folder))
    jobs = {m.job: m for m in journal if isinstance(m, TrainJob)}
    acked = tuple(sorted((m.agent, m.job) for m in journal if isinstance(m, Ack)))
    return Whole(folder, journal, Knowledge(idle, frozenset(jobs), acked), jobs)


def test_the_checker_accepts_a_whole_run(whole: Whole) -> None:
    assert len(whole.knowledge.acked) == sum(isinstance(m, Birth) for m in whole.journal) == 10
    assert journal_holds(whole.folder, whole.knowledge, "at the end", finished=True) == []


def test_a_child_born_twice_is_rejected(whole: Whole, tmp_path: Path) -> None:
    """The run's last birth journaled again, in a segment of its own (as a coordinator
    restarted on the run would write it, had it forgotten the birth)."""
    folder = whole.copy(tmp_path / "run")
    birth = whole.last_birth()
    with Journal(folder) as journal:
        journal.write(birth)
    assert journal_holds(folder, whole.knowledge, "at the end", finished=True) == [
        f"at the end: {birth.agent} born 2 times"
    ]


@pytest.mark.parametrize("which", ["first", "last"])
def test_an_acknowledged_birth_without_its_trainers_checkpoint_is_rejected(
    whole: Whole, tmp_path: Path, which: str
) -> None:
    """A checkpoint file removed (the Ack went out before it was on the disk), or holding another
    child's policy: at the start of a coordinator on the folder and at the end of the run it
    finishes (its trainers, told, never send that report again)."""
    births = [m for m in whole.journal if isinstance(m, Birth)]
    child = (births[0] if which == "first" else births[-1]).agent
    folder = whole.copy(tmp_path / "run")
    (folder / "checkpoints" / f"{child}.pt").unlink()
    missing = f"acknowledged {child}'s checkpoint file is missing or not its trainer's"
    assert journal_holds(folder, whole.knowledge, "at the start") == [f"at the start: {missing}"]
    assert check(folder, whole.knowledge, whole.jobs) == [
        f"at the start: {missing}",
        f"at the end: {missing}",
        f"at the end: {child} has no checkpoint file",
    ]

    other = next(b.agent for b in births if b.agent != child)
    (folder / "checkpoints" / f"{child}.pt").write_bytes(
        (folder / "checkpoints" / f"{other}.pt").read_bytes()
    )
    assert journal_holds(folder, whole.knowledge, "at the start") == [f"at the start: {missing}"]


def test_a_best_body_without_its_checkpoint_is_rejected(whole: Whole, tmp_path: Path) -> None:
    """The run's results written before the best body's checkpoint was in place."""
    folder = whole.copy(tmp_path / "run")
    best = sorted((folder / "best").iterdir())[0]
    (best / "checkpoint.pt").unlink()
    assert journal_holds(folder, whole.knowledge, "at the end", finished=True) == [
        f"at the end: {best.name} of the best has no checkpoint.pt"
    ]


def test_a_journal_that_lost_what_the_trainers_were_told_is_rejected(
    whole: Whole, tmp_path: Path
) -> None:
    """The journal without its tail from the run's last job on (what a crash leaves of a journal
    whose writes were published before they were on the disk), written by the real journal
    writer: the last job was received, and its birth acknowledged, yet neither is journaled."""
    last = max(k for k, m in enumerate(whole.journal) if isinstance(m, TrainJob))
    job = whole.journal[last]
    assert isinstance(job, TrainJob)
    folder = tmp_path / "run"
    with Journal(folder) as journal:
        for msg in whole.journal[:last]:
            journal.write(msg)
    shutil.copytree(whole.folder / "checkpoints", folder / "checkpoints")
    problems = journal_holds(folder, whole.knowledge, "at the start")
    assert f"at the start: job {job.job}, received by a trainer, is not in the journal" in problems
    assert (f"at the start: acknowledged birth of {job.agent} (job {job.job}) is not in the "
            "journal (born from None)") in problems  # fmt: skip
    born = {m.agent for m in whole.journal[:last] if isinstance(m, Birth)}
    assert all(f"of {child} " not in p for child in born for p in problems)  # the rest holds
