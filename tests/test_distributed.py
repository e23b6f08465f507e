"""The distributed run, with real processes on real Zenoh (loopback, multicast off): a whole
smoke run, and runs that survive a trainer SIGKILLed or SIGSTOPped mid-training, a coordinator
SIGKILLed and restarted (with a torn journal tail), and garbage on every key; a node that does not
grow by the sessions that come and go."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack
import pytest
from nodes_fixtures import (
    SMOKE_RUN,
    FinishedRun,
    LocalRun,
    Observer,
    Processes,
    assert_born_once,
    births,
    derl_argv,
    free_port,
    in_training,
    jobs,
    journaled,
    observe,
)

from derl.messages import Birth, FitnessReport, JobLost, encode
from derl.messages.examples import examples
from derl.messages.types import MAX_MESSAGE_BYTES
from derl.nodes.journal.segments import replay, segments
from derl.nodes.runtime.bus import ZenohOptions, open_session, zenoh_config
from derl.nodes.testing.processes import sample
from derl.nodes.testing.waiting import wait_until

PROFILE = {
    "total": 4,
    "train_steps": 16384,  # 8 PPO iterations, ~2 s a body: time to interrupt a training
    "lease_s": 20.0,
}


@pytest.fixture
def local(tmp_path: Path) -> LocalRun:
    return LocalRun.at(tmp_path, **PROFILE)


@pytest.fixture
def observer(local: LocalRun) -> Iterator[Observer]:
    """A session of the test itself, hearing the run's status and progress."""
    with observe(local) as seen:
        yield seen


@pytest.mark.slow
@SMOKE_RUN
def test_smoke_run_end_to_end(smoke_run: FinishedRun) -> None:
    run_dir, result = smoke_run
    assert "done: 8 bodies" in result.stdout
    lines = result.stdout.splitlines()
    # stdout is no terminal (a log file): plain timestamped progress lines, nothing wrapped
    stamp = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d"
    assert any(re.match(rf"{stamp} evolution: \d/8 born, best ", line) for line in lines)
    assert any(line.startswith("run ") and f"logs in {run_dir / 'logs'}" in line for line in lines)
    births = [m for m in replay(run_dir) if isinstance(m, Birth)]
    assert len({m.agent for m in births}) == len(births) == 8
    assert len(list((run_dir / "checkpoints").glob("*.pt"))) == 8
    assert (run_dir / "summary.json").exists() and any((run_dir / "best").iterdir())
    assert {"patrol", "incline"} == {m.task for m in replay(run_dir) if m.type == "EvalResult"}


@pytest.mark.slow
def test_killed_trainer_loses_nothing(
    local: LocalRun, procs: Processes, observer: Observer
) -> None:
    procs.start("coordinator", local.coordinator())
    procs.start("victim", local.trainer("victim"))
    procs.start("survivor", local.trainer("survivor"))
    heard = observer.training("victim")
    procs.kill("victim")
    lost = wait_until(lambda: [m for m in journaled(local.dir, JobLost) if m.node == "victim"],
                      local.lease_s + 10, "the victim's job lost")  # fmt: skip
    assert [m.job for m in lost] == [heard.job]  # killed holding the job heard in its first half
    child = heard.agent
    wait_until(lambda: len(births(local.dir)) == 4, 300, "every body born")
    assert_born_once(local.dir, 4)
    holders = [job.node for job in jobs(local.dir) if job.agent == child]
    assert holders[0] == "victim" and "survivor" in holders[1:]


@pytest.mark.slow
def test_stopped_trainer_is_noticed_within_its_lease(
    local: LocalRun, procs: Processes, observer: Observer
) -> None:
    procs.start("coordinator", local.coordinator())
    frozen = procs.start("frozen", local.trainer("frozen"))
    procs.start("other", local.trainer("other"))
    progress = observer.training("frozen")
    job = progress.job
    os.killpg(frozen.pid, signal.SIGSTOP)
    stopped = time.monotonic()
    try:
        lost = wait_until(
            lambda: [m for m in journaled(local.dir, JobLost) if m.job == job],
            local.lease_s + 30,
            "the frozen trainer's job lost",
        )
        noticed = time.monotonic() - stopped
        # the transport lease (2.5 s) or the job's lease, whichever is first, and the journal read
        assert noticed < local.lease_s + 3, (noticed, lost)
        # still frozen, so its late report cannot win the race: once the other trainer is done
        # with its own body, the child is handed to it
        wait_until(
            lambda: [j for j in jobs(local.dir) if j.agent == progress.agent and j.node == "other"],
            120,
            "the child handed to the other trainer",
        )
    finally:
        os.killpg(frozen.pid, signal.SIGCONT)
    wait_until(lambda: len(births(local.dir)) == 4, 300, "every body born")
    assert_born_once(local.dir, 4)


@pytest.mark.slow
def test_coordinator_restart_loses_nothing(
    local: LocalRun, procs: Processes, observer: Observer
) -> None:
    procs.start("coordinator", local.coordinator())
    procs.start("a", local.trainer("a"))
    procs.start("b", local.trainer("b"))
    wait_until(lambda: len(births(local.dir)) >= 2 and in_training(local.dir), 180,
               "two births and a child in training")  # fmt: skip
    procs.kill("coordinator")
    before = births(local.dir)
    assert len(before) < 4, before
    segment = segments(local.dir)[-1]
    with segment.open("ab") as torn:  # a write cut short by the kill
        torn.write(b"\x05garbage-tail")
    time.sleep(2)  # trainers keep training and re-sending while no coordinator is up
    procs.start("coordinator", local.coordinator())
    wait_until(lambda: len(births(local.dir)) == 4, 300, "every body born after the restart")
    assert_born_once(local.dir, 4)
    assert births(local.dir)[: len(before)] == before
    assert len(segments(local.dir)) == 2
    assert "journaled messages replayed" in procs.log("coordinator")


@pytest.mark.slow
def test_garbage_on_every_key_is_rejected(tmp_path: Path, procs: Processes) -> None:
    # a run far longer than the test (which stops it): still going while its rejections are
    # counted, on a machine of any speed
    local = LocalRun.at(tmp_path, **{**PROFILE, "total": 1000})
    with observe(local) as observer:
        _garbage_on_every_key(local, procs, observer)


def _garbage_on_every_key(local: LocalRun, procs: Processes, observer: Observer) -> None:
    coordinator = procs.start("coordinator", local.coordinator())
    trainer = procs.start("t", local.trainer("t"))
    wait_until(lambda: observer.progress, 120, "training to start")
    keys = observer.bus.keys
    targets = [keys.ready("t"), keys.job("t"), keys.ack("t"), keys.fitness("t", "x"),
               keys.progress("t", "x"), keys.eval("t", "x", "ft"), keys.status(),
               keys.population(), keys.tournament("x"), keys.births("x")]  # fmt: skip
    valid = examples(local.run, 0, 10)
    wrong_version = {**valid[0].model_dump(), "schema_version": 99}
    forged = FitnessReport.model_validate({**next(m for m in valid if m.type == "FitnessReport")
                                           .model_dump(), "job": "never-issued"})  # fmt: skip
    for key in targets:
        for payload in (b"\xff\x00garbage", msgpack.packb(wrong_version), msgpack.packb([1, 2]),
                        msgpack.packb({"type": "TrainJob", "schema_version": 1, "run": local.run,
                                       "genome": {"limbs": [{"id": -1}]}})):  # fmt: skip
            observer.bus.session.put(key, payload)
    observer.bus.publish(forged)
    wait_until(lambda: observer.statuses and observer.statuses[-1].rejected >= 10, 30, "rejections")
    assert coordinator.poll() is None and trainer.poll() is None
    assert "never issued" in procs.log("coordinator")
    assert "rejected" in procs.log("t")
    wait_until(lambda: len(births(local.dir)) >= 1, 180, "the run going on")


# A client of the user's own (Zenoh's default config: shared memory on; multicast off) sending
# large samples, as a trainer sends its checkpoints
OWN_CLIENT = """
import json, os, re, subprocess, sys, time, zenoh
config = zenoh.Config()
for key, value in (("mode", "client"), ("connect/endpoints", [sys.argv[1]]),
                   ("scouting/multicast/enabled", False), ("connect/timeout_ms", 30000)):
    config.insert_json5(key, json.dumps(value))
count, size = (int(a) for a in sys.argv[2:4]) if len(sys.argv) > 2 else (20, 10_000)

def delivered():  # what this process sent to the router and had acknowledged, with nothing
    try:          # left in its sockets (`ss`), else 0
        said = subprocess.run(["ss", "-tinpH", "state", "established", "dst",
                               sys.argv[1].split("/")[1]], capture_output=True, text=True).stdout
    except OSError:
        return 0
    acked, mine = 0, False
    for line in said.splitlines():
        if not line[:1].isspace():  # a socket: Recv-Q Send-Q local peer users
            mine = f"pid={os.getpid()}," in line
            if mine and line.split()[1] != "0":
                return 0
        elif mine and (found := re.search("bytes_acked:([0-9]+)", line)):
            acked += int(found[1])
    return acked

with zenoh.open(config) as session:
    for _ in range(count):  # over the size Zenoh moves by shared memory, as a checkpoint is
        session.put("derl/churn/x", bytes(size), congestion_control=zenoh.CongestionControl.BLOCK)
    # a large sample goes out in fragments after `put` returns: open until the router has them
    # (measured: all but 45 kB of 80 MB had reached it then, the rest 50 ms later), or, where
    # `ss` says nothing, for a while (4 s for 40 MB)
    deadline = time.monotonic() + size / 1e7
    while delivered() < count * size and time.monotonic() < deadline:
        time.sleep(0.01)
"""


def test_a_node_does_not_grow_by_the_sessions_that_come_and_go(procs: Processes) -> None:
    """Zenoh 1.x negotiates shared memory with every session from another process on the same
    host by default, and a router or peer then kept about 19 MB for each one that ever
    connected and sent it large samples (each trainer or evaluator restarted): the soak's
    coordinator and router grew by it. derl's sessions have shared memory off, so even clients
    of Zenoh's default config coming and going leave a node within a few MB."""
    router = f"tcp/127.0.0.1:{free_port()}"
    process = procs.start("router", derl_argv("router", "--listen", router))

    def client_comes_and_goes() -> None:
        subprocess.run([sys.executable, "-c", OWN_CLIENT, router], check=True, timeout=60)

    heard: list[int] = []
    with open_session(ZenohOptions(mode="client", connect=(router,))) as session:
        session.declare_subscriber("derl/churn/**", lambda sample: heard.append(1))
        client_comes_and_goes()  # the router's own warm-up
        before = sample(process.pid)["rss_mb"]
        for _ in range(8):
            client_comes_and_goes()
        grown = sample(process.pid)["rss_mb"] - before
    assert heard  # the router forwarded them
    assert grown < 20, f"the router grew by {grown:.1f} MB over 8 sessions"


def test_an_oversized_sample_stops_at_the_transport(procs: Processes) -> None:
    """Zenoh takes messages of up to 1 GiB by default: a 40 MB sample from a client of Zenoh's
    default config reached every subscriber (which then had to decode it). derl's sessions take
    none larger than `MAX_MESSAGE_BYTES` (a margin above a checkpoint's report): the router
    drops them before assembling them, stays flat over them, and goes on forwarding the
    others."""
    router = f"tcp/127.0.0.1:{free_port()}"
    process = procs.start("router", derl_argv("router", "--listen", router))

    def client(count: int, size: int) -> None:
        argv = [sys.executable, "-c", OWN_CLIENT, router, str(count), str(size)]
        subprocess.run(argv, check=True, timeout=120)

    heard: list[int] = []
    with open_session(ZenohOptions(mode="client", connect=(router,))) as session:
        session.declare_subscriber("derl/churn/**", lambda s: heard.append(len(s.payload)))
        client(1, 1000)  # the router's own warm-up
        wait_until(lambda: heard, 10, "a small sample")
        for _ in range(2):  # the transport's buffers, once (measured: +28 MB, then +2 MB)
            client(2, 40_000_000)
        before = sample(process.pid)["rss_mb"]
        for _ in range(3):
            client(2, 40_000_000)
        grown = sample(process.pid)["rss_mb"] - before
        client(1, 1000)
        wait_until(lambda: len(heard) >= 2, 10, "a small sample after the large ones")
    assert heard == [1000, 1000]
    # a sample assembled adds its 40 MB (a 50 MB one kept 49 MB before the bound): 240 MB over
    # six; the allocator's noise over them was up to 13 MB
    assert grown < 40, f"the router grew by {grown:.1f} MB over six more 40 MB samples"


def test_worker_defaults_keep_multicast_and_shared_memory_off() -> None:
    config = zenoh_config(ZenohOptions())
    assert '"enabled":false' in config.get_json("scouting/multicast").replace(" ", "")
    assert config.get_json("transport/shared_memory/enabled") == "false"
    assert config.get_json("transport/link/rx/max_message_size") == str(MAX_MESSAGE_BYTES)
    assert encode(examples("r", 0, 0)[0])
