"""A worker's first WorkerReady goes out once the coordinator's subscription is known to its
session: one sent before is lost, and a neighbour took the waiting job meanwhile (seen in CI: a
2-trainer launch where one trainer did every job)."""

from __future__ import annotations

import queue
import threading
import time

from messages import KeySpace
from nodes.runtime.bus import ZenohOptions, open_session
from nodes.worker.node import Worker, ready_wait
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
            time.sleep(0.5)  # the worker is up; nobody subscribes to WorkerReady yet
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
