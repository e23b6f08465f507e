"""The crash run: a small real run recorded under strace, with simulated trainers, and its crash
states (`derl.nodes.testing.disk`), each with what the trainers knew then.

A small real run (the smoke profile: P=4, T=2, 10 bodies, no evaluation) of a real
`derl coordinator` process and two simulated trainers (`Trainer`: each answers its job at once
with its body, a fitness and checkpoint bytes that depend only on the child, and sends the report
again every 0.5 s until it is acknowledged or rejected, as `derl trainer` does) over real Zenoh,
under `strace -f`: every open, write (with its bytes), truncate, rename, link, unlink, mkdir,
fsync, fdatasync and syncfs of the coordinator and its checkpoint writer process, and every mark
of a trainer (a job received, an Ack, a Reject, written to a file of marks), in the order they
completed (a trainer marks a message after receiving it, so after every operation the coordinator
did before publishing it). `record_and_cut` records it and makes every crash state of it, told
apart as a coordinator's start sees them; `derl.nodes.testing.crash_check` checks them.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import yaml

from derl.evolution import EvolutionConfig, load_profile
from derl.messages import (
    Ack,
    Birth,
    Cancel,
    FitnessReport,
    MessageBase,
    Reject,
    RunStatus,
    TrainJob,
    WorkerReady,
)
from derl.nodes.journal.reader import JournalDamaged
from derl.nodes.journal.segments import cut_torn_tail, replay, segments
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.runtime.ports import free_port
from derl.nodes.testing.disk import Cut, Knowledge, Op, build, cuts, normalized, parse_trace
from derl.nodes.testing.trainers import fake_report, policy_of

RUN = "crash"
PROFILE = {"profile": "smoke", "total": 10, "eval_top": 0, "eval_tasks": [], "lease_s": 60.0}
NODES = ("t1", "t2")
RESEND_S = 0.5
SYSCALLS = ("openat,creat,write,pwrite64,writev,pwritev,pwritev2,lseek,ftruncate,truncate,"
            "rename,renameat,renameat2,link,linkat,unlink,unlinkat,mkdir,mkdirat,fsync,"
            "fdatasync,syncfs,sync,close")  # fmt: skip


def config() -> EvolutionConfig:
    """The run's profile, as `derl coordinator --profile crash.yaml` reads it."""
    fields = {k: v for k, v in PROFILE.items() if k != "profile"}
    base = load_profile(str(PROFILE["profile"])).model_dump()
    return EvolutionConfig.model_validate({**base, **fields, "name": "crash"})


# --- the simulated trainers ------------------------------------------------------------------


@cache
def report_of(job: TrainJob) -> FitnessReport:
    """`job`'s report (`fake_report`, with the job's body) with this child's checkpoint
    (`policy_of`) and fitness: later children are fitter (as evolution hopes), so the last ones
    born are the best, whose checkpoints the run's results must hold."""
    fitness = int(job.agent[1:]) + (50.0 if job.agent.startswith("c") else 0.0)
    report = fake_report(job.run, job, fitness)
    checkpoint = policy_of(job.agent, job.genome, job.task)
    return report.model_copy(update={"env_steps": job.steps, "checkpoint": checkpoint})


@dataclass
class Trainer:
    """What a simulated trainer does with what it hears, whatever carries its messages: a job is
    answered at once, and the report sent again (`pending`) until acknowledged or rejected."""

    node: str
    job: TrainJob | None = None
    acknowledged: bool = True  # its job's report is answered (or it has none)
    marks: list[str] = field(default_factory=list)

    def hear(self, msg: MessageBase) -> list[MessageBase]:
        """What it sends in answer to `msg` (a job, an Ack or Reject, a Cancel of its node)."""
        if isinstance(msg, TrainJob):
            if self.job is not None and msg.job == self.job.job and not self.acknowledged:
                return []  # the order sent again while it answers: its report goes on
            self.job, self.acknowledged = msg, False
            self.marks.append(f"job {self.node} {msg.job} {msg.agent}")
            return [report_of(msg)]
        if isinstance(msg, Ack | Reject) and self.job is not None and msg.job == self.job.job:
            if not self.acknowledged:
                kind = "ack" if isinstance(msg, Ack) else "reject"
                self.marks.append(f"{kind} {self.node} {msg.job} {msg.agent}")
            self.acknowledged = True
            return [self.ready()]
        if isinstance(msg, Cancel) and self.job is not None and msg.job == self.job.job:
            self.acknowledged = True
            return [self.ready()]
        return []

    def pending(self) -> FitnessReport | None:
        return None if self.acknowledged or self.job is None else report_of(self.job)

    def ready(self) -> WorkerReady:
        return WorkerReady(run=RUN, node=self.node, role="trainer", host="sim", pid=1)

    def again(self) -> MessageBase:
        """What it sends while it waits: its report again, or another ask for work."""
        pending = self.pending()
        return self.ready() if pending is None else pending


def zenoh_trainers(endpoint: str, trainers: list[Trainer], marks: Path | None,
                   timeout: float = 300.0) -> None:  # fmt: skip
    """Run `trainers` on one Zenoh session until the run is done (each mark appended to `marks`
    by a write of its own, so `strace` orders it among the coordinator's operations)."""
    lock = threading.Lock()
    done = threading.Event()
    out = os.open(marks, os.O_WRONLY | os.O_CREAT | os.O_APPEND) if marks else None
    with open_session(ZenohOptions(connect=(endpoint,))) as session:
        bus = Bus(session, RUN)
        tokens = [bus.token("trainer", t.node) for t in trainers]

        def hearing(trainer: Trainer) -> Callable[[MessageBase], None]:
            def on(msg: MessageBase) -> None:
                with lock:
                    before = len(trainer.marks)
                    answers = trainer.hear(msg)
                    for mark in trainer.marks[before:]:
                        if out is not None:
                            os.write(out, f"{mark}\n".encode())
                for answer in answers:
                    bus.publish(answer)

            return on

        for trainer in trainers:
            bus.subscribe(bus.keys.job(trainer.node), hearing(trainer), (TrainJob, Cancel))
            bus.subscribe(bus.keys.ack(trainer.node), hearing(trainer), (Ack, Reject))

        def on_status(status: MessageBase) -> None:
            if isinstance(status, RunStatus) and status.done:
                done.set()

        bus.subscribe(bus.keys.status(), on_status, (RunStatus,))
        deadline = time.monotonic() + timeout
        while True:  # until the run is done and no report waits for its answer
            if done.wait(RESEND_S):
                time.sleep(RESEND_S)
            if time.monotonic() > deadline:
                raise TimeoutError("the run did not finish")
            with lock:
                waiting = [t.again() for t in trainers if not done.is_set() or t.pending()]
            if not waiting:
                break
            for msg in waiting:
                bus.publish(msg)
        for token in tokens:
            token.undeclare()
    if out is not None:
        os.close(out)


RECORDED = (
    "import logging, pathlib, sys; from derl.nodes.testing.crash import record_run; "
    "logging.basicConfig(level=logging.ERROR); record_run(pathlib.Path(sys.argv[1]))"
)  # the process `record` runs under strace


def record_run(work: Path) -> None:
    """The recorded run: its coordinator, and its trainers in this process (`record` runs it
    under strace)."""
    from derl.nodes.runtime.processes import spawn_derl, stop_all

    profile = work / "crash.yaml"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    coordinator = spawn_derl(
        ["coordinator", "--run", RUN, "--profile", str(profile), "--run-dir", str(work / "run"),
         "--listen", endpoint], work / "coordinator.log",
    )  # fmt: skip
    try:
        zenoh_trainers(endpoint, [Trainer(node) for node in NODES], work / "marks")
        if coordinator.wait(60) != 0:
            raise RuntimeError(f"the coordinator failed: {(work / 'coordinator.log').read_text()}")
    finally:
        stop_all([coordinator])


def record(work: Path) -> Path:
    """Run the small run under strace in `work`; the trace's path."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "crash.yaml").write_text(yaml.safe_dump(PROFILE))
    trace = work / "trace"
    done = subprocess.run(
        ["strace", "-f", "-qq", "-y", "-xx", "-s", "100000000", "--seccomp-bpf", "-e",
         f"trace={SYSCALLS}",
         "-o", str(trace), sys.executable, "-c", RECORDED, str(work)],
        capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"the recorded run failed:\n{done.stdout}\n{done.stderr}")
    return trace


def trainers_at(knowledge: Knowledge, jobs: dict[str, TrainJob]) -> list[Trainer]:
    """The two trainers as they were at a cut."""
    return [Trainer(node, None if job is None else jobs[job], answered)
            for node, job, answered in knowledge.holding]  # fmt: skip


# --- every cut ---------------------------------------------------------------------------------


@dataclass
class Recorded:
    """A recorded run and its crash states."""

    work: Path
    ops: list[Op]
    jobs: dict[str, TrainJob]  # every job of the run, by id
    tried: Counter[str]  # states by kind
    distinct: list[Cut]  # one state of each distinct (normalized state, knowledge)
    refused: list[dict[str, object]]  # states a start refuses (a failure)
    seconds: float


def record_and_cut(work: Path) -> Recorded:
    """Record the run in `work`, then every crash state of it, normalized and told apart."""
    started = time.monotonic()
    trace = record(work)
    run_dir = work / "run"
    ops = parse_trace(trace, run_dir, work / "marks")
    jobs = {m.job: m for m in replay(run_dir) if isinstance(m, TrainJob)}
    tried: Counter[str] = Counter()
    distinct: dict[tuple[str, Knowledge], Cut] = {}
    refused = []
    scratch = work / "states"
    scratch.mkdir()
    for cut in cuts(ops, run_dir, NODES):
        tried[cut.kind] += 1
        try:
            key = (normalized(cut.state, scratch / "segment.mcap"), cut.knowledge)
        except JournalDamaged as damage:
            refused.append(failure(cut, [f"the start refuses it: {damage}"]))
            continue
        distinct.setdefault(key, cut)
    return Recorded(work, ops, jobs, tried, list(distinct.values()), refused,
                    time.monotonic() - started)  # fmt: skip


def journaled(recorded: Recorded, cut: Cut) -> list[MessageBase]:
    """The messages of a state's journal, as a start reads them (its torn tail cut)."""
    folder = Path(tempfile.mkdtemp(prefix="journal-", dir=recorded.work))
    build({k: v for k, v in cut.state.items() if k.startswith("journal")}, folder / "run")
    try:
        if found := segments(folder / "run"):
            cut_torn_tail(found[-1])
        return list(replay(folder / "run"))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def last_checkpoint_late(recorded: Recorded) -> Cut:
    """A kill just after the run's last birth was journaled, before its checkpoint file was in
    place. Which of the two the recorded run wrote first is up to its two processes' timing, so
    where the checkpoint came first the state is made from the first kill state with every birth
    journaled, less the checkpoint files of the births not yet acknowledged: what the other
    order leaves (the Ack waits for both, so the trainers' knowledge is the same)."""
    # every cut in order: `distinct` keeps a state once, under the first cut that left it
    for cut in cuts(recorded.ops, recorded.work / "run", NODES):
        if cut.kind != "kill":
            continue
        births = {m.agent for m in journaled(recorded, cut) if isinstance(m, Birth)}
        if len(births) < config().total:
            continue
        late = births - {child for child, _ in cut.knowledge.acked}
        state = {name: content for name, content in cut.state.items() if not (
            name.startswith("checkpoints/") and name[12:].split(".pt")[0] in late)}  # fmt: skip
        return Cut(cut.index, "kill", state, cut.knowledge)
    raise RuntimeError("the recorded run never journaled its last birth")


def failure(cut: Cut, problems: list[str], real: bool = False) -> dict[str, object]:
    """How a state that broke something is reported."""
    return {"cut": cut.index, "kind": cut.kind, "torn_at": cut.torn_at, "real": real,
            "problems": problems[:5]}  # fmt: skip
