"""The distributed run, with real processes on real Zenoh (loopback, multicast off): a whole
smoke run, and runs that survive a trainer SIGKILLed or SIGSTOPped mid-training, a coordinator
SIGKILLed and restarted (with a torn journal tail), and garbage on every key."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from nodes_fixtures import free_port, wait_for

from messages import Birth, FitnessReport, RunStatus, TrainJob, TrainProgress, encode
from messages.examples import examples
from nodes.journal.segments import replay, segments
from nodes.runtime.bus import Bus, ZenohOptions, open_session
from nodes.runtime.processes import spawn_derl, stop_all

PROFILE = {
    "profile": "smoke",
    "population": 2,
    "tournament": 2,
    "total": 4,
    "train_steps": 49152,  # a few seconds per body: time to interrupt a training
    "num_envs": 16,
    "lease_s": 20.0,
    "eval_top": 0,
    "eval_tasks": [],
}


class Cluster:
    """Nodes of one run on loopback, each in its own process group, all killed at the end."""

    def __init__(self, tmp: Path, profile: dict[str, object]) -> None:
        self.run = f"t{uuid.uuid4().hex[:10]}"
        self.dir = tmp / "run"
        self.logs = tmp / "logs"
        self.logs.mkdir()
        self.profile = tmp / "profile.yaml"
        self.profile.write_text(yaml.safe_dump(profile))
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.processes: list[subprocess.Popen] = []
        self.statuses: list[RunStatus] = []
        self.progress: list[TrainProgress] = []

    def coordinator(self) -> subprocess.Popen:
        return self._spawn(
            "coordinator",
            ["coordinator", "--profile", str(self.profile), "--run-dir", str(self.dir),
             "--run", self.run, "--listen", self.endpoint],
        )  # fmt: skip

    def trainer(self, name: str) -> subprocess.Popen:
        args = ["trainer", "--run", self.run, "--connect", self.endpoint, "--name", name]
        return self._spawn(name, args)

    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen:
        process = spawn_derl(args, self.logs / f"{name}.log")
        self.processes.append(process)
        return process

    def births(self) -> list[str]:
        if not segments(self.dir):
            return []
        return [m.child for m in replay(self.dir) if isinstance(m, Birth)]

    def jobs(self) -> list[TrainJob]:
        return [m for m in replay(self.dir) if isinstance(m, TrainJob)]

    def log(self, name: str) -> str:
        return (self.logs / f"{name}.log").read_text()

    def close(self) -> None:
        stop_all(self.processes, timeout=5)


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    nodes = Cluster(tmp_path, PROFILE)
    try:
        yield nodes
    finally:
        nodes.close()


@pytest.fixture
def observer(cluster: Cluster) -> Iterator[Bus]:
    """A session of the test itself, seeing the run's status and progress."""
    with open_session(ZenohOptions(connect=(cluster.endpoint,))) as session:
        bus = Bus(session, cluster.run)
        bus.subscribe(bus.keys.status(), cluster.statuses.append, (RunStatus,))
        bus.subscribe(bus.keys.all("progress"), cluster.progress.append, (TrainProgress,))
        yield bus


def _assert_born_once(cluster: Cluster, total: int) -> None:
    births = cluster.births()
    assert len(births) == total, births
    assert max(Counter(births).values()) == 1, births


@pytest.mark.slow
def test_smoke_run_end_to_end(tmp_path: Path) -> None:
    run_dir = tmp_path / "smoke"
    result = subprocess.run(
        [sys.executable, "-m", "nodes.cli", "run", "--profile", "smoke", "--run-dir", str(run_dir)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    assert "done: 8 bodies" in result.stdout
    births = [m for m in replay(run_dir) if isinstance(m, Birth)]
    assert len({m.child for m in births}) == len(births) == 8
    assert len(list((run_dir / "checkpoints").glob("*.pt"))) == 8
    assert (run_dir / "summary.json").exists() and any((run_dir / "best").iterdir())
    assert {"patrol", "incline"} == {m.task for m in replay(run_dir) if m.type == "EvalResult"}


@pytest.mark.slow
def test_killed_trainer_loses_nothing(cluster: Cluster, observer: Bus) -> None:
    cluster.coordinator()
    victim = cluster.trainer("victim")
    cluster.trainer("survivor")
    progress = wait_for(
        lambda: [p for p in cluster.progress if p.node == "victim"], 120, "the victim training"
    )
    child = progress[0].child
    os.killpg(victim.pid, signal.SIGKILL)
    wait_for(lambda: len(cluster.births()) == 4, 300, "every body born")
    _assert_born_once(cluster, 4)
    holders = [job.node for job in cluster.jobs() if job.child == child]
    assert holders[0] == "victim" and "survivor" in holders[1:]


@pytest.mark.slow
def test_stopped_trainer_is_noticed_within_its_lease(cluster: Cluster, observer: Bus) -> None:
    cluster.coordinator()
    frozen = cluster.trainer("frozen")
    cluster.trainer("other")
    progress = wait_for(
        lambda: [p for p in cluster.progress if p.node == "frozen"], 120, "the frozen training"
    )
    child = progress[0].child
    os.killpg(frozen.pid, signal.SIGSTOP)
    stopped = time.monotonic()
    try:
        wait_for(
            lambda: [j for j in cluster.jobs() if j.child == child and j.node == "other"],
            60,
            "the child handed to the other trainer",
        )
        noticed = time.monotonic() - stopped
    finally:
        os.killpg(frozen.pid, signal.SIGCONT)
    # the transport lease is 2.5 s; the other trainer may still be busy with its own body
    assert "frozen left" in cluster.log("coordinator")
    wait_for(lambda: len(cluster.births()) == 4, 300, "every body born")
    _assert_born_once(cluster, 4)
    assert noticed < 60


@pytest.mark.slow
def test_coordinator_restart_loses_nothing(cluster: Cluster, observer: Bus) -> None:
    first = cluster.coordinator()
    cluster.trainer("a")
    cluster.trainer("b")
    wait_for(lambda: len(cluster.births()) >= 2, 180, "two births")
    os.killpg(first.pid, signal.SIGKILL)
    first.wait()
    before = cluster.births()
    segment = segments(cluster.dir)[-1]
    with segment.open("ab") as torn:  # a write cut short by the kill
        torn.write(b"\x05garbage-tail")
    time.sleep(2)  # trainers keep training and re-sending while no coordinator is up
    cluster.coordinator()
    wait_for(lambda: len(cluster.births()) == 4, 300, "every body born after the restart")
    _assert_born_once(cluster, 4)
    assert cluster.births()[: len(before)] == before
    assert len(segments(cluster.dir)) == 2
    assert "journaled messages replayed" in cluster.log("coordinator")


@pytest.mark.slow
def test_garbage_on_every_key_is_rejected(cluster: Cluster, observer: Bus) -> None:
    coordinator = cluster.coordinator()
    trainer = cluster.trainer("t")
    wait_for(lambda: cluster.progress, 120, "training to start")
    keys = observer.keys
    targets = [keys.ready("t"), keys.job("t"), keys.ack("t"), keys.fitness("t", "x"),
               keys.progress("t", "x"), keys.eval("t", "x", "ft"), keys.status(),
               keys.population(), keys.tournament("x"), keys.births("x")]  # fmt: skip
    valid = examples(cluster.run, 0, 10)
    wrong_version = {**valid[0].model_dump(), "schema_version": 99}
    forged = FitnessReport.model_validate({**next(m for m in valid if m.type == "FitnessReport")
                                           .model_dump(), "job": "never-issued"})  # fmt: skip
    import msgpack

    for key in targets:
        for payload in (b"\xff\x00garbage", msgpack.packb(wrong_version), msgpack.packb([1, 2]),
                        msgpack.packb({"type": "TrainJob", "schema_version": 1, "run": cluster.run,
                                       "genome": {"limbs": [{"id": -1}]}})):  # fmt: skip
            observer.session.put(key, payload)
    observer.publish(forged)
    wait_for(lambda: cluster.statuses and cluster.statuses[-1].rejected >= 10, 30, "rejections")
    assert coordinator.poll() is None and trainer.poll() is None
    assert "never issued" in cluster.log("coordinator")
    assert "rejected" in cluster.log("t")
    wait_for(lambda: len(cluster.births()) >= 1, 180, "the run going on")


def test_worker_defaults_keep_multicast_off() -> None:
    from nodes.runtime.bus import zenoh_config

    config = zenoh_config(ZenohOptions())
    assert '"enabled":false' in config.get_json("scouting/multicast").replace(" ", "")
    assert encode(examples("r", 0, 0)[0])
