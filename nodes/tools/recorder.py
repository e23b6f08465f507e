"""`derl record` and `derl replay`: live traffic into an MCAP log, and a log back onto the bus.

Recording taps each key expression through a ring (`nodes.tools.topic.Tap`: a recorder that falls
behind loses the oldest samples, it never stalls the run) and appends every valid message with the
journal's writer (`nodes.journal.segments.JournalWriter`: msgpack messages on ``derl/<run>/<kind>``
channels with the models' JSON schemas, flushed message by message, so a killed recorder leaves a
readable file). Log time is the receive time; publish time is the sender's Zenoh timestamp when it
has one. Malformed payloads are logged and counted but not kept: a recording holds only messages
that decode, like a journal, so every reader (replay, export, `report`) can use it.

Replaying refuses a damaged log (one `derl log info` calls corrupt: damage a crash cannot leave)
unless told to skip the damage; a torn tail is no damage. It reads the log with the tolerant reader
(which skips a damaged part and reads on) and publishes each message on its own key
(`KeySpace.key_for`) with the original gaps divided by the rate, BLOCK like the control plane: a
subscriber that cannot keep up slows the replay, never loses messages; monitors read through rings
and are never slowed. A replay must not pose as a live run: jobs and acks published under a run that
has live nodes would be taken as real. So it refuses a run that has a live node or coordinator on
the bus (unless forced), and `as_run` publishes everything under another run id. A replay nobody
hears (no subscriber matched any key it published on: Zenoh's matching status) says so once, after
`UNHEARD_S` or at its end.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh

from derl.messages import MessageBase, kind_of
from derl.nodes.journal.segments import JournalWriter
from derl.nodes.runtime.bus import Bus, ZenohOptions, matched, open_session
from derl.nodes.tools.logs import LogError, info, read_log
from derl.nodes.tools.topic import Checker, Tap, live_runs, resolve

log = logging.getLogger("derl.recorder")

RECORD_RING = 16_384
"""Samples the recorder may fall behind by before the oldest are dropped."""

UNHEARD_S = 5.0
"""A replay that nobody has heard for this long since it began says so (a shorter one, at its
end)."""

SETTLE_S = 0.5
"""How long a replay that nobody heard waits at its end for late news of subscribers (a client
session learns of them from its router a round trip after asking)."""


@dataclass
class Recorded:
    messages: int
    rejected: Counter[str]
    seconds: float


def record(
    options: ZenohOptions,
    out: Path,
    keys: list[str],
    run: str | None,
    duration: float | None,
    stop: threading.Event,
) -> Recorded:
    """Record every valid message on `keys` into a new file `out` until `stop` or `duration`."""
    start = time.monotonic()
    taps: list[Tap] = []
    writer: JournalWriter | None = None
    written = 0
    lock = threading.Lock()  # the taps' threads share the writer and the counts
    try:
        with open_session(options) as session:
            exprs = [resolve(session, key, run) for key in keys]
            writer = JournalWriter(out)
            checker = Checker(session)

            def on_sample(sample: zenoh.Sample, _: float) -> None:
                nonlocal written
                with lock:
                    message = checker.check(str(sample.key_expr), sample.payload.to_bytes())
                    if message is not None:
                        writer.write(message, _publish_time(sample))
                        written += 1

            taps = [Tap(session, expr, on_sample, RECORD_RING) for expr in exprs]
            log.info("recording %s into %s", ", ".join(exprs), out)
            stop.wait(duration)
    finally:  # closing the session ends the taps' threads (what their rings held is dropped)
        for tap in taps:
            tap.join()
        if writer is not None:
            writer.close()
    return Recorded(written, checker.rejected, time.monotonic() - start)


def _publish_time(sample: zenoh.Sample) -> int | None:
    if sample.timestamp is None:
        return None
    return int(sample.timestamp.get_time().timestamp() * 1e9)


class ReplayRefused(RuntimeError):
    """The log's run is live on the bus: replaying it would feed its nodes old jobs and acks."""


@dataclass
class Replayed:
    messages: int
    passes: int
    seconds: float


class Audience:
    """Whether any subscriber matches what a session publishes: a probe publisher (never put on)
    for each key published on, read as each message goes out, until one matches."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.probes: dict[str, zenoh.Publisher] = {}
        self.heard = False

    def published(self, key: str) -> None:
        if self.heard:
            return
        probe = self.probes.get(key)
        if probe is None:
            probe = self.probes[key] = self.session.declare_publisher(key)
        if matched(probe):
            self._found()

    def settle(self, timeout: float) -> bool:
        """Whether a subscriber matched, asking the probes again for up to `timeout` s."""
        deadline = time.monotonic() + timeout
        while not self.heard:
            if any(matched(probe) for probe in self.probes.values()):
                self._found()
            elif time.monotonic() >= deadline:
                break
            else:
                time.sleep(0.05)
        return self.heard

    def _found(self) -> None:
        self.heard = True
        self.close()

    def close(self) -> None:
        for probe in self.probes.values():
            probe.undeclare()
        self.probes.clear()


def replay(
    options: ZenohOptions,
    source: Path,
    stop: threading.Event,
    rate: float = 1.0,
    loop: bool = False,
    kinds: frozenset[str] = frozenset(),
    start_offset: float = 0.0,
    as_run: str | None = None,
    only_run: str | None = None,
    force: bool = False,
    skip_damaged: bool = False,
    unheard: Callable[[int, bool], None] = lambda published, ended: None,
) -> Replayed:
    """Publish the messages of `source` with their original timing divided by `rate` (0: at
    once), skipping the first `start_offset` seconds; only `kinds` (key kinds) if given, only
    `only_run` if given, under run `as_run` if given; again and again with `loop`. A damaged
    log (`derl log info` says corrupt) is refused unless `skip_damaged`: then what can be read
    of it is replayed. `unheard(published, ended)` is told once when no subscriber has matched
    what was published: `UNHEARD_S` after the start, or at the end of a shorter replay."""
    for file in info(source):  # a bad log fails before joining the bus
        if file.integrity == "corrupt" and not skip_damaged:
            raise LogError(
                f"{file.path}: {file.detail}. `derl log repair {file.path} OUT.mcap` "
                "writes a clean copy of what can be read; --skip-damaged replays that as it is"
            )
    published = passes = 0
    told = False
    with open_session(options) as session:
        live = set() if force else set(live_runs(session))
        buses: dict[str, Bus] = {}
        audience = Audience(session)
        start = time.monotonic()

        def publish(message: MessageBase) -> None:
            if as_run is not None:
                message = message.model_copy(update={"run": as_run})
            if message.run in live:
                raise ReplayRefused(
                    f"run {message.run} is live on this bus: replaying it would feed its nodes "
                    "old jobs and acks; use --as-run NEW (or --force)"
                )
            bus = buses.get(message.run) or buses.setdefault(message.run, Bus(session, message.run))
            bus.publish(message)
            audience.published(bus.keys.key_for(message))

        while not stop.is_set():
            first: int | None = None  # log time of the log's first message
            begun: float | None = None  # when offset 0 (log time start + start_offset) is due
            before = published
            for logged in read_log(source):
                first = logged.log_time if first is None else first
                offset = (logged.log_time - first) / 1e9 - start_offset
                if offset < 0:
                    continue
                if begun is None and rate > 0:
                    begun = time.monotonic() - offset / rate
                message = logged.message
                if only_run and message.run != only_run:
                    continue
                if kinds and kind_of(message) not in kinds:
                    continue
                delay = 0.0 if begun is None else begun + offset / rate - time.monotonic()
                if stop.wait(max(0.0, delay)):
                    break
                publish(message)
                published += 1
                if not (told or audience.heard) and time.monotonic() - start >= UNHEARD_S:
                    told = True
                    unheard(published, False)
            passes += 1
            log.info("pass %d: %d messages published so far", passes, published)
            if not loop or published == before:
                break
        seconds = time.monotonic() - start
        if published and not told and not audience.settle(SETTLE_S):
            unheard(published, True)
        audience.close()
    return Replayed(published, passes, seconds)
