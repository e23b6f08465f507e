"""A small run through a schedule of faults, with real processes on real Zenoh (loopback,
multicast off): garbage on every key kind, a job that fails, a trainer SIGKILLed mid-job (and
started again), a trainer SIGSTOPped past its lease (then SIGCONT) and, while it is stopped, the
coordinator SIGKILLed and restarted. Every child is born once or given up (ChildFailed), the run
finishes, every node exits by itself. Per fault it prints the time to notice, the time to recover,
and the births lost or duplicated (`pytest -s` shows them)."""

from __future__ import annotations

import os
import signal
import socket
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest
from nodes_fixtures import LocalRun, Processes, births, journaled, observe

from derl.messages import (
    Birth,
    ChildFailed,
    JobFailed,
    JobLost,
    MessageBase,
    TrainJob,
    TrainProgress,
    WorkerReady,
)
from derl.nodes.runtime.bus import Bus
from derl.nodes.testing.faults import put_garbage
from derl.nodes.testing.processes import with_arguments
from derl.nodes.testing.waiting import wait_until
from derl.nodes.tools.logs import read_log

PROFILE = {
    "total": 14,  # one child in flight (TINY_PROFILE): a faulted job stalls the run, so few are
    # born before the coordinator's kill (up to 8 on a fast machine, most while a restarts)
    "train_steps": 16384,  # 8 PPO iterations of 16 envs x 128 steps: time to interrupt one
    "lease_s": 8.0,
    "max_attempts": 1,  # a failed training gives its child up
}
TRAINERS = ("a", "b")


class Saboteur:
    """A trainer played by the test: it asks for work, reports the first job it gets failed (the
    JobFailed a training that raises sends), and leaves once told (a node that leaves holding a
    job loses it, and its JobFailed may come after)."""

    def __init__(self, bus: Bus, node: str) -> None:
        self.bus, self.node = bus, node
        self.jobs: list[TrainJob] = []
        bus.subscribe(bus.keys.job(node), self.jobs.append, (TrainJob,))
        self.token = bus.token("trainer", node)

    def ask(self) -> TrainJob | None:
        """Its job, or None after one more WorkerReady."""
        if self.jobs:
            return self.jobs[0]
        host = socket.gethostname() or "host"
        ready = WorkerReady(run=self.bus.run, node=self.node, role="trainer", host=host,
                            pid=os.getpid())  # fmt: skip
        self.bus.publish(ready)
        return None

    def fail(self, job: TrainJob) -> None:
        self.bus.publish(JobFailed(run=self.bus.run, job=job.job, node=self.node,
                                   agent=job.agent, error="RuntimeError: sabotaged"))  # fmt: skip

    def leave(self) -> None:
        self.token.undeclare()


def _lost(run_dir: Path, progress: TrainProgress) -> Callable[[], list[JobLost]]:
    """The JobLosts of the job of `progress` in the journal so far."""
    return lambda: [m for m in journaled(run_dir, JobLost) if m.job == progress.job]


Timeline = list[tuple[float, MessageBase]]  # (journal time in s since the epoch, message)


def _job_fault(timeline: Timeline, job: str, child: str, at: float) -> dict[str, object]:
    """What the journal says followed a fault at `at` to the holder of `job` (of `child`): the
    job lost or failed (noticed), the child's next job, birth or giving up (recovered), and how
    many times the child was born."""
    noticed = next(t for t, m in timeline if isinstance(m, (JobLost, JobFailed)) and m.job == job)
    issued = next(i for i, (_, m) in enumerate(timeline) if getattr(m, "job", None) == job)
    recovered = next(
        t for t, m in timeline[issued + 1 :]
        if (isinstance(m, TrainJob) and m.agent == child)
        or (isinstance(m, (Birth, ChildFailed)) and m.agent == child)
    )  # fmt: skip
    born = sum(isinstance(m, Birth) and m.agent == child for _, m in timeline)
    return {"noticed_s": round(noticed - at, 1), "recovered_s": round(recovered - at, 1),
            "agent": child, "births": born}  # fmt: skip


@pytest.mark.slow
def test_a_run_survives_a_schedule_of_faults(tmp_path: Path, procs: Processes) -> None:
    local = LocalRun.at(tmp_path, **PROFILE)
    lease = local.lease_s
    at: dict[str, float] = {}  # when each fault was made, s since the epoch
    procs.start("coordinator", local.coordinator())
    for name in TRAINERS:
        procs.start(name, local.trainer(name))
    with observe(local) as observer:
        bus = observer.bus
        wait_until(lambda: observer.statuses, 60, "the coordinator's status")

        # a job that fails: its child given up (max_attempts 1)
        saboteur = Saboteur(bus, "saboteur")
        failed = wait_until(saboteur.ask, 60, "a job for the saboteur")
        at["failed job"] = time.time()
        saboteur.fail(failed)
        wait_until(lambda: journaled(local.dir, ChildFailed), 30, "the child given up")
        saboteur.leave()

        # garbage on every key kind: rejected, counted, nobody falls over (once the test's
        # session hears trainer a: a peer's puts reach another peer once the two are linked)
        observer.training("a", timeout=60)
        at["garbage"] = time.time()
        put, _stray = put_garbage(bus)
        coordinator_kinds = 5 * 4  # ready, fitness, progress, eval, failure: all four payloads
        wait_until(lambda: observer.statuses[-1].rejected >= coordinator_kinds, 30, "rejections")
        garbage_noticed = round(time.time() - at["garbage"], 1)
        assert all(procs.started[n].poll() is None for n in ("coordinator", *TRAINERS))

        # a trainer SIGKILLed mid-job, then started again under its name
        killed = observer.training("a", len(observer.progress))
        at["SIGKILL trainer"] = time.time()
        procs.kill("a")
        wait_until(_lost(local.dir, killed), lease + 10, "the killed trainer's job lost")
        procs.start("a", local.trainer("a"))

        # a trainer SIGSTOPped past its lease (then SIGCONT), and, once its job is lost, the
        # coordinator SIGKILLed and restarted on its endpoint a second later: the run is still
        # mid-way whatever the machine's speed (the other trainer breeds on while one is frozen)
        frozen = observer.training("b", len(observer.progress))
        at["SIGSTOP trainer"] = time.time()
        os.killpg(procs.started["b"].pid, signal.SIGSTOP)
        try:
            wait_until(_lost(local.dir, frozen), lease + 10, "the stopped trainer's job lost")
            born = len(births(local.dir))
            print(f"chaos: {born} born at the coordinator's kill")
            assert born < PROFILE["total"] - 2, "the run got too far before the coordinator's kill"
            at["SIGKILL coordinator"] = time.time()
            procs.kill("coordinator")
            before = births(local.dir)
            time.sleep(1)
            heard = len(observer.statuses)
            coordinator = procs.start("coordinator-2", local.coordinator())
            wait_until(lambda: len(observer.statuses) > heard, 60, "the restarted coordinator")
            coordinator_back = round(time.time() - at["SIGKILL coordinator"], 1)
            time.sleep(max(0.0, at["SIGSTOP trainer"] + lease + 2 - time.time()))
        finally:
            os.killpg(procs.started["b"].pid, signal.SIGCONT)
        assert procs.finish(coordinator, timeout=240) == 0, procs.log("coordinator-2")
    ended = time.monotonic()
    for name in TRAINERS:  # told the run is done, each trainer ends by itself
        assert procs.finish(procs.started[name], timeout=30) == 0, procs.log(name)
    trainers_ended = round(time.monotonic() - ended, 1)
    assert not [p.pid for p in procs.every if p.poll() is None]
    assert not with_arguments("--run", local.run)  # no node of the run left, let alone spinning

    born = births(local.dir)
    given_up = [m.agent for m in journaled(local.dir, ChildFailed)]
    assert given_up == [failed.agent], (given_up, failed.job)
    assert failed.agent not in born, (failed.job, born)
    assert [m.job for m in journaled(local.dir, JobFailed)] == [failed.job]
    assert max(Counter(born).values()) == 1, born  # none born twice
    assert len(born) + len(given_up) == PROFILE["total"]  # none lost
    assert born[: len(before)] == before  # the restart kept the journal's births
    assert "ignored liveliness token" in procs.log("coordinator")
    assert "rejected (malformed) derl/" in procs.log("a")  # its job and ack keys, the status
    timeline = [(logged.log_time / 1e9, logged.message) for logged in read_log(local.dir)]
    after_restart = next(t for t, m in timeline if isinstance(m, Birth) and m.agent not in before)
    faults = {
        "failed job": _job_fault(timeline, failed.job, failed.agent, at["failed job"]),
        "garbage": {"noticed_s": garbage_noticed, "payloads": put, "births": len(born)},
        "SIGKILL trainer": _job_fault(timeline, killed.job, killed.agent, at["SIGKILL trainer"]),
        "SIGSTOP trainer": _job_fault(timeline, frozen.job, frozen.agent, at["SIGSTOP trainer"]),
        "SIGKILL coordinator": {
            "noticed_s": coordinator_back,  # its status heard again, restarted after 1 s
            "recovered_s": round(after_restart - at["SIGKILL coordinator"], 1),
            "births": len(born),
        },
    }
    for name, fault in faults.items():
        print(f"chaos: {name}: {fault}")
    print(f"chaos: the trainers ended {trainers_ended} s after the coordinator")
    assert faults["SIGSTOP trainer"]["noticed_s"] <= lease + 3  # within its lease
    assert faults["SIGKILL trainer"]["births"] == faults["SIGSTOP trainer"]["births"] == 1
