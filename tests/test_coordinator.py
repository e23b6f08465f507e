"""The coordinator's handlers on a real Zenoh session: group commit (nothing is published before
the journal file holds it) and checkpoint files (an Ack only once the file is on disk, and a
lost file written again from the repeated report)."""

from __future__ import annotations

import logging
import queue
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from derl.evolution import load_profile
from derl.unimal import sample_population
from messages import Ack, Birth, Curve, FitnessReport, MessageBase, TrainJob, WorkerReady, decode
from nodes.coordinator.node import INITIAL_FILE, Coordinator
from nodes.journal.segments import read_segment
from nodes.runtime.bus import Bus, ZenohOptions, open_session
from tests.nodes_fixtures import free_port, run_id

QUIET_S = 0.5  # how long "nothing was published" is watched for


@pytest.fixture
def coordinator(tmp_path: Path) -> Iterator[tuple[Coordinator, queue.Queue[MessageBase]]]:
    """A coordinator of a 2-body run whose bus is a real Zenoh session, and a queue of what an
    observer in another session hears it publish."""
    run = run_id()
    config = load_profile("smoke").model_copy(update={"population": 2, "total": 3})
    initial = sample_population(2, np.random.default_rng(3))
    (tmp_path / INITIAL_FILE).write_text("[" + ",".join(g.model_dump_json() for g in initial) + "]")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    heard: queue.Queue[MessageBase] = queue.Queue()
    with (
        open_session(ZenohOptions(listen=(endpoint,))) as own,
        open_session(ZenohOptions(connect=(endpoint,))) as observer,
    ):
        subscriber = observer.declare_subscriber(
            f"derl/{run}/**", lambda sample: heard.put(decode(sample.payload.to_bytes()))
        )
        coordinator = Coordinator(run, tmp_path, config)
        coordinator.bus = Bus(own, run)
        try:
            yield coordinator, heard
        finally:
            subscriber.undeclare()
            coordinator.checkpoints.close()
            coordinator.journal.close()


def _quiet(heard: queue.Queue[MessageBase]) -> bool:
    try:
        heard.get(timeout=QUIET_S)
    except queue.Empty:
        return True
    return False


def _journaled(coordinator: Coordinator) -> list[MessageBase]:
    return list(read_segment(coordinator.journal.segment))


def _ready(coordinator: Coordinator, node: str) -> None:
    coordinator._ready(WorkerReady(run=coordinator.run, node=node, role="trainer", host="h", pid=1))


def _job_for(coordinator: Coordinator, node: str) -> TrainJob:
    _ready(coordinator, node)
    coordinator._flush()
    job = coordinator.state.job_of(node)
    assert job is not None and isinstance(job.order, TrainJob)
    return job.order


def _report(job: TrainJob, checkpoint: bytes) -> FitnessReport:
    return FitnessReport(
        run=job.run, child=job.child, job=job.job, node=job.node, genome=job.genome,
        fitness=1.0, fitness_source="window", fitness_episodes=1,
        curve=Curve(env_steps=(1, 2), returns=(0.0, 1.0)), energy=1.0, cost_of_work=1.0,
        mass=1.0, episodes=1, env_steps=2, wall_s=0.0, steps_per_s=0.0, checkpoint=checkpoint,
    )  # fmt: skip


def test_a_job_is_published_only_once_the_journal_file_holds_it(
    coordinator: tuple[Coordinator, queue.Queue[MessageBase]],
) -> None:
    node, (coordinator, heard) = "w1", coordinator
    _ready(coordinator, node)
    assert not [m for m in _journaled(coordinator) if isinstance(m, TrainJob)]
    assert _quiet(heard), "a job went out before the journal file had it"

    coordinator._flush()
    sent = heard.get(timeout=10)
    assert isinstance(sent, TrainJob) and sent.node == node
    assert sent in _journaled(coordinator)


def test_an_ack_waits_for_its_checkpoint_and_a_lost_one_is_written_again(
    coordinator: tuple[Coordinator, queue.Queue[MessageBase]],
    caplog: pytest.LogCaptureFixture,
) -> None:
    coordinator, heard = coordinator
    first, second = _job_for(coordinator, "w1"), _job_for(coordinator, "w2")
    assert isinstance(heard.get(timeout=10), TrainJob)
    assert isinstance(heard.get(timeout=10), TrainJob)

    # accepted: the Ack comes, and the checkpoint file is whole by then
    coordinator._fitness(_report(first, b"weights-1"))
    coordinator._flush()
    assert isinstance(heard.get(timeout=10), Birth)  # the birth stream: journaled, published
    ack = heard.get(timeout=10)
    assert isinstance(ack, Ack) and ack.child == first.child
    assert coordinator.checkpoints.path(first.child).read_bytes() == b"weights-1"

    # the write fails (the folder is gone, a file in its place): born, but not acknowledged
    folder = coordinator.checkpoints.folder
    shutil.rmtree(folder)
    folder.write_text("not a folder")
    report = _report(second, b"weights-2")
    with caplog.at_level(logging.ERROR, logger="derl.coordinator"):
        coordinator._fitness(report)
        coordinator._flush()
    assert isinstance(heard.get(timeout=10), Birth)
    assert second.child in coordinator.state.evolution.fitness
    assert report.model_copy(update={"checkpoint": b""}) in _journaled(coordinator)
    assert _quiet(heard), "an Ack went out for a checkpoint that is not on disk"
    assert "checkpoint was not written" in caplog.text

    # the trainer sends its report again: the checkpoint is written, then acknowledged
    folder.unlink()
    folder.mkdir()
    coordinator._fitness(report)
    coordinator._flush()
    ack = heard.get(timeout=10)
    assert isinstance(ack, Ack) and ack.child == second.child
    assert coordinator.checkpoints.path(second.child).read_bytes() == b"weights-2"
    assert coordinator.born == 2
