"""A worker's first WorkerReady goes out once the coordinator's subscription is known to its
session: one sent before is lost, and a neighbour took the waiting job meanwhile (seen in CI: a
2-trainer launch where one trainer did every job). An idle worker asks less and less often, and
says when it hears no coordinator of its run."""

from __future__ import annotations

import logging
import queue
import threading
import time

import pytest

from derl.messages import KeySpace, RunStatus
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.testing.waiting import ManualClock, wait_until
from derl.nodes.worker.node import UNHEARD_S, Worker, ready_wait
from tests.nodes_fixtures import free_port, run_id


def test_a_worker_asks_for_work_as_soon_as_a_coordinator_would_hear_it() -> None:
    run, endpoint = run_id(), f"tcp/127.0.0.1:{free_port()}"
    heard: queue.Queue[float] = queue.Queue()
    with open_session(ZenohOptions(listen=(endpoint,))) as coordinator_side:
        worker = Worker(run, "trainer-ready-test", "trainer")
        thread = threading.Thread(
            target=worker.serve, args=(ZenohOptions(connect=(endpoint,)),), daemon=True
        )
        thread.start()
        subscriber = None
        try:
            # the worker is up, its WorkerReady ready to go; nobody subscribes to it yet
            wait_until(lambda: getattr(worker, "asking", None), 10, "the worker's publisher")
            declared = time.monotonic()
            subscriber = coordinator_side.declare_subscriber(
                KeySpace(run).all("ready"), lambda _: heard.put(time.monotonic())
            )
            first = heard.get(timeout=10)
            # sent blind, the first one is lost and the next comes a second later
            assert first - declared < 0.4, f"first WorkerReady {first - declared:.2f} s late"
        finally:
            worker.stop.set()
            thread.join(timeout=10)
            if subscriber is not None:
                subscriber.undeclare()
        assert not thread.is_alive()


def test_an_idle_worker_asks_less_and_less_often() -> None:
    """After 1, 2, 4, then every 8 s: the coordinator sends a job to a worker that asked as soon
    as there is one, so asking again only recovers from a lost message or a restart."""
    assert [ready_wait(asks) for asks in range(6)] == [1.0, 2.0, 4.0, 8.0, 8.0, 8.0]


def test_a_worker_that_hears_no_coordinator_says_so_once_and_when_it_hears_one(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A mistyped run id or endpoint must not look like a quiet run: an idle worker that hears no
    status of its run says so once, and says when a coordinator is heard. Its clock runs fast
    (`UNHEARD_S` each time the test looks): it says so after its first wait for a job."""
    run, endpoint = run_id(), f"tcp/127.0.0.1:{free_port()}"
    clock = ManualClock()
    worker = Worker(run, "trainer-unheard-test", "trainer", clock=clock)
    with open_session(ZenohOptions(listen=(endpoint,))) as coordinator_side:
        thread = threading.Thread(
            target=worker.serve, args=(ZenohOptions(connect=(endpoint,)),), daemon=True
        )
        with caplog.at_level(logging.INFO, logger="derl.worker"):
            thread.start()
            try:
                wait_until(lambda: clock.advance(UNHEARD_S) or worker.unheard, 15,
                           "the worker to say it hears no coordinator")  # fmt: skip
                status = RunStatus(run=run, born=0, target=8, best_fitness=None, best_agent=None,
                                   in_flight=0, workers_alive=1)  # fmt: skip
                bus = Bus(coordinator_side, run)
                wait_until(
                    lambda: bus.publish(status) or not worker.unheard, 10, "the status heard"
                )
            finally:
                worker.stop.set()
                thread.join(timeout=10)
    said = [r.getMessage() for r in caplog.records if "coordinator of run" in r.getMessage()]
    assert len(said) == 2, said
    assert f"no coordinator of run {run} heard for" in said[0] and "check --run" in said[0]
    assert said[1].endswith(f"the coordinator of run {run} is heard")
