"""`derl foxglove`: a run's streams served live to Foxglove over its WebSocket protocol.

A bridge between the bus and the `foxglove-sdk` WebSocket server. It taps the run's births,
status and progress keys through rings (`nodes.tools.topic.Tap`: a bridge that falls behind loses
the oldest samples, it never slows the run) and first asks the coordinator for the births so far
(the Zenoh query `derl monitor` makes), so a bridge started late is complete. Each key family is
one Foxglove channel with encoding ``json`` and the message type's JSON schema in the form the
viewers' parser reads (`nodes.tools.viewer_schema`; the one `derl export` writes), so the plots
and tables of Foxglove and Lichtblick read its fields: ``/derl/births`` (Birth, each birth
once), ``/derl/births/failed`` (ChildFailed), ``/derl/status`` (RunStatus) and
``/derl/progress`` (TrainProgress). Topics do not name the run
(the server's name does), so one layout, docs/foxglove-layout.json, fits every run.

Foxglove keeps no history for a client that connects late, and the protocol has no latched
topics, so the bridge also publishes ``/derl/summary`` every second (`RunSummary`): fitness and
best fitness of every birth so far in birth order (for a plot against the birth index), the latest
births, and steps/s per worker, each worker in a fixed slot in the order first heard.
The SDK's server keeps a bounded queue per client and drops the oldest data when a client is slow.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from itertools import accumulate

import foxglove
import zenoh
from foxglove.websocket import WebSocketServer
from pydantic import BaseModel

from derl.messages import Birth, ChildFailed, KeySpace, MessageBase, RunStatus, TrainProgress
from derl.messages.dispatch import Handler, handles
from derl.nodes.runtime.bus import ZenohOptions, open_session
from derl.nodes.tools.logs import base64_text, json_form, json_schema
from derl.nodes.tools.topic import Checker, Tap, ask, choose_run
from derl.nodes.tools.viewer_schema import viewer_schema

KINDS = ("births", "status", "progress")
"""The key families the bridge serves."""
TOPICS: dict[str, str] = {
    Birth.__name__: "/derl/births",
    ChildFailed.__name__: "/derl/births/failed",
    RunStatus.__name__: "/derl/status",
    TrainProgress.__name__: "/derl/progress",
}
"""Message type -> its Foxglove topic."""
SUMMARY_TOPIC = "/derl/summary"
SUMMARY_S = 1.0
RECENT_BIRTHS = 10
STALE_S = 5.0
"""A worker not heard for this long shows 0 steps/s (progress comes every second)."""


class CannotServe(OSError):
    """The WebSocket server could not start (the port is taken, the host is not ours)."""


class BirthRow(BaseModel):
    birth: int
    agent: str
    parent: str | None
    mutation: str | None
    fitness: float
    node: str


class WorkerSpeed(BaseModel):
    node: str
    agent: str
    steps_per_s: float


class RunSummary(BaseModel):
    """What a late client needs at once: the whole fitness curve, the latest births, the workers."""

    run: str
    births: list[int]
    fitness: list[float]
    best: list[float]
    """Best fitness so far, after each birth."""
    recent: list[BirthRow]
    """The latest births, newest first."""
    workers: list[WorkerSpeed]
    """One slot per worker, in the order first heard."""


class Bridge(Handler):
    """Messages of one run onto Foxglove channels of `context`; thread-safe."""

    def __init__(self, run: str, context: foxglove.Context) -> None:
        self.run = run
        self._channels = {
            kind: foxglove.Channel(topic, schema=json_schema(kind), context=context)
            for kind, topic in TOPICS.items()
        }
        self._summary = foxglove.Channel(
            SUMMARY_TOPIC, schema=viewer_schema(RunSummary), context=context
        )
        self._lock = threading.Lock()
        self._births: dict[int, Birth] = {}
        self._failed: set[str] = set()
        self._workers: dict[str, tuple[TrainProgress, float]] = {}

    def apply(self, msg: MessageBase, now: float) -> None:
        """Log `msg` on its channel (a birth or failure already seen is not logged again)."""
        if msg.run != self.run or msg.type not in self._channels:
            return
        with self._lock:
            if self.dispatch(msg, now) is False:
                return
        self._channels[msg.type].log(json_form(msg, base64_text))

    @handles(Birth)
    def _birth(self, msg: Birth, now: float) -> bool:
        """Whether it is new (kept for the summary)."""
        new = msg.birth not in self._births
        self._births.setdefault(msg.birth, msg)
        return new

    @handles(ChildFailed)
    def _failure(self, msg: ChildFailed, now: float) -> bool:
        """Whether it is new."""
        new = msg.agent not in self._failed
        self._failed.add(msg.agent)
        return new

    @handles(TrainProgress)
    def _progress(self, msg: TrainProgress, now: float) -> bool:
        self._workers[msg.node] = (msg, now)
        return True

    def summary(self, now: float) -> RunSummary:
        with self._lock:
            births = [self._births[k] for k in sorted(self._births)]
            workers = list(self._workers.values())
        return RunSummary(
            run=self.run,
            births=[b.birth for b in births],
            fitness=[b.fitness for b in births],
            best=list(accumulate((b.fitness for b in births), max)),
            recent=[
                BirthRow(
                    birth=b.birth,
                    agent=b.agent,
                    parent=b.parent,
                    mutation=b.mutation,
                    fitness=b.fitness,
                    node=b.node,
                )
                for b in reversed(births[-RECENT_BIRTHS:])
            ],
            workers=[
                WorkerSpeed(
                    node=p.node,
                    agent=p.agent,
                    steps_per_s=p.steps_per_s if now - heard < STALE_S else 0.0,
                )
                for p, heard in workers
            ],
        )

    def publish_summary(self, now: float) -> None:
        self._summary.log(self.summary(now).model_dump(mode="json"))


def serve(
    options: ZenohOptions,
    run: str | None,
    host: str,
    port: int,
    stop: threading.Event,
    started: Callable[[str, WebSocketServer], None] = lambda run, server: None,
) -> Bridge:
    """Serve run `run` (or the only run on the bus) on ws://host:port until `stop`;
    `started(run, server)` is called once the server listens."""
    context = foxglove.Context()
    taps: list[Tap] = []
    with open_session(options) as session:
        bridge = Bridge(choose_run(session, run), context)
        checker = Checker(session)

        def on_sample(sample: zenoh.Sample, arrival: float) -> None:
            message = checker.check(str(sample.key_expr), sample.payload.to_bytes())
            if message is not None:
                bridge.apply(message, arrival)

        keys = KeySpace(bridge.run)
        taps = [Tap(session, keys.all(kind), on_sample) for kind in KINDS]
        ask(session, keys.all("births"), on_sample)  # births before we came
        try:
            server = foxglove.start_server(
                name=f"derl {bridge.run}", host=host, port=port, context=context
            )
        except RuntimeError as error:  # the SDK's FoxgloveError
            raise CannotServe(f"cannot serve on ws://{host}:{port}: {error}") from None
        try:
            started(bridge.run, server)
            while not stop.wait(SUMMARY_S):
                bridge.publish_summary(time.monotonic())
        finally:
            server.stop()
    for tap in taps:
        tap.join()
    return bridge
