"""The crash checker: what a run directory left by a crash must hold, and a coordinator started on
it that runs the run to its end.

Invariants (`journal_holds`): every job a trainer had received is in the journal; every birth
whose Ack a trainer had received is in the journal, from that job, with its checkpoint file
holding that trainer's bytes; no child is born twice; and once the run is over: every body born,
each with its checkpoint file, summary.json and the best bodies' folders with their checkpoints.
A state is checked (`check`) by a coordinator started on it (it must start: a crash never leaves
what it refuses), which runs the run to its end with the trainers as they were at the cut: one
that held a job and had not heard its Ack sends its report again, the others ask for work
(`derl trainer` after a coordinator restart); the invariants must hold at the start and at the
end. `check` drives the coordinator's own code in this process (`Coordinator` built on the
folder: the replay and everything a start does; then its handlers, group commit and outbox as the
serve loop calls them, and the loop's end: five rounds of 'done', the results written at the
last; without a bus: what it publishes goes to the trainers); `check_real` does it with a real
`derl coordinator` process and the trainers over real Zenoh.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
import time
from collections import Counter
from pathlib import Path

import yaml

from derl.agent_folder import CHECKPOINT
from derl.messages import Birth, MessageBase, TrainJob, decode, encode
from derl.nodes.coordinator.node import DONE_ANNOUNCEMENTS, Coordinator, Liveliness
from derl.nodes.coordinator.run.rules import EvolutionRules
from derl.nodes.journal.segments import cut_torn_tail, replay, segments
from derl.nodes.runtime.ports import free_port
from derl.nodes.runtime.processes import spawn_derl, stop_all
from derl.nodes.testing.crash import (
    PROFILE,
    RUN,
    Recorded,
    config,
    failure,
    trainers_at,
    zenoh_trainers,
)
from derl.nodes.testing.disk import Cut, Knowledge, build
from derl.nodes.testing.trainers import Recorder, policy_of


def journal_holds(folder: Path, knowledge: Knowledge, when: str, finished: bool = False
                  ) -> list[str]:  # fmt: skip
    """What the run directory `folder`'s journal and checkpoint files break of the invariants,
    given what the trainers knew (`knowledge`), each problem starting with `when`; with
    `finished`, of those of a run that is over too (none broken: [])."""
    problems = []
    journal = list(replay(folder))
    issued = {m.job for m in journal if isinstance(m, TrainJob)}
    for job in sorted(knowledge.received - issued):
        problems.append(f"{when}: job {job}, received by a trainer, is not in the journal")
    births = Counter(m.agent for m in journal if isinstance(m, Birth))
    born_from = {m.agent: m.job for m in journal if isinstance(m, Birth)}
    bodies = {m.agent: m.genome for m in journal if isinstance(m, Birth)}
    for child, job in knowledge.acked:
        if born_from.get(child) != job:
            problems.append(f"{when}: acknowledged birth of {child} (job {job}) is not in the "
                            f"journal (born from {born_from.get(child)})")  # fmt: skip
        elif _checkpoint(folder, child) != policy_of(child, bodies[child], config().world):
            problems.append(f"{when}: acknowledged {child}'s checkpoint file is missing or not "
                            "its trainer's")  # fmt: skip
    problems += [f"{when}: {child} born {n} times" for child, n in births.items() if n > 1]
    if finished:
        total = config().total
        if len(births) != total:
            problems.append(f"{when}: {len(births)} born of {total}")
        for child in births:
            if _checkpoint(folder, child) is None:
                problems.append(f"{when}: {child} has no checkpoint file")
        if not (folder / "summary.json").is_file():
            problems.append(f"{when}: no summary.json")
        for best in sorted((folder / "best").glob("*")):
            if not (best / CHECKPOINT).is_file():
                problems.append(f"{when}: {best.name} of the best has no {CHECKPOINT}")
    return problems


def _checkpoint(folder: Path, child: str) -> bytes | None:
    path = folder / "checkpoints" / f"{child}.pt"
    return path.read_bytes() if path.is_file() else None


def check(folder: Path, knowledge: Knowledge, jobs: dict[str, TrainJob]) -> list[str]:
    """Start a coordinator on `folder` in this process, run the run to its end with the trainers
    as they were (`knowledge`; `jobs`: every job of the run, by id), and say what broke (nothing:
    [])."""
    heard = Recorder()
    try:
        rules = EvolutionRules(RUN, folder, config())
        coordinator = Coordinator(RUN, folder, rules, publisher=heard)
    except (SystemExit, Exception) as refused:  # a refusal, or a fault
        return [f"the coordinator did not start: {refused!r}"]
    problems = journal_holds(folder, knowledge, "at the start")
    trainers = {t.node: t for t in trainers_at(knowledge, jobs)}
    for node in trainers:  # each holds its liveliness token
        coordinator.take(Liveliness("trainer", node, True))
    try:
        inbox: list[MessageBase] = [t.again() for t in trainers.values()]
        after = 0  # rounds since the run finished: its serve loop goes on while it says so
        for _ in range(2000):
            after += coordinator.state.finished
            if after == DONE_ANNOUNCEMENTS:  # as the serve loop does before it ends
                coordinator.settle()
                coordinator.rules.finish()
                break
            for msg in inbox:
                coordinator.take(decode(encode(msg)))
            coordinator.assign_idle()
            coordinator.settle()
            inbox = []
            for msg in heard.messages:
                to = getattr(msg, "node", None)
                if to in trainers:
                    inbox += trainers[to].hear(msg)
            heard.messages.clear()
            if not inbox:  # nothing answered: each sends its report again or asks again
                inbox = [t.again() for t in trainers.values()]
        else:
            problems.append(f"the run did not finish: {coordinator.rules.progress().born} born")
    finally:
        coordinator.close()
    return problems + journal_holds(folder, knowledge, "at the end", finished=True)


def check_real(folder: Path, knowledge: Knowledge, jobs: dict[str, TrainJob]) -> list[str]:
    """The same with a real `derl coordinator` process and the trainers over real Zenoh."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    log = folder.parent / f"{folder.name}.log"
    profile = folder.parent / "crash.yaml"
    profile.write_text(yaml.safe_dump(PROFILE))
    coordinator = spawn_derl(
        ["coordinator", "--run", RUN, "--profile", str(profile), "--run-dir", str(folder),
         "--listen", endpoint], log,
    )  # fmt: skip
    problems = []
    try:
        time.sleep(0.5)
        if coordinator.poll() is not None:
            return [f"the coordinator refused to start: {log.read_text().strip()[-300:]}"]
        zenoh_trainers(endpoint, trainers_at(knowledge, jobs), None, timeout=120)
        if coordinator.wait(60) != 0:
            problems.append(f"the coordinator failed: {log.read_text().strip()[-300:]}")
    except (TimeoutError, subprocess.TimeoutExpired) as error:
        problems.append(f"{error}")
    finally:
        stop_all([coordinator])
    return problems + journal_holds(folder, knowledge, "at the end", finished=True)


def check_cut(recorded: Recorded, cut: Cut, real: bool = False) -> dict[str, object] | None:
    """Check one state (in this process, or with real processes); its failure, if any."""
    folder = Path(tempfile.mkdtemp(prefix="state-", dir=recorded.work))
    shutil.rmtree(folder)
    build(cut.state, folder)
    try:
        problems = (check_real if real else check)(folder, cut.knowledge, recorded.jobs)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return failure(cut, problems, real) if problems else None


def holds_at_start(recorded: Recorded, cut: Cut) -> list[str]:
    """What a state breaks of the invariants a start must find (every job a trainer received
    and every acknowledged birth with its checkpoint in place), without running the run."""
    folder = Path(tempfile.mkdtemp(prefix="state-", dir=recorded.work))
    shutil.rmtree(folder)
    build(cut.state, folder)
    try:
        if found := segments(folder):
            cut_torn_tail(found[-1])
        return journal_holds(folder, cut.knowledge, "at the start")
    finally:
        shutil.rmtree(folder, ignore_errors=True)
