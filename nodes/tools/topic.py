"""Watching live traffic without disturbing it, and `derl topic list|echo|hz`.

`Tap` is how every watcher (topic, monitor, record) subscribes: a `RingChannel`, which drops the
oldest sample when full and so never stalls a publisher, not even one using BLOCK
(docs/bus.md), drained by a daemon thread that hands each sample to a short
function; the thread ends when the session closes. `Checker` validates samples of any run with
`Bus.check` (so garbage is logged and counted, never fatal). `choose_run` finds the run to watch
when none is given: runs with a live node or a coordinator publishing `derl/<run>/status`.
A KEY argument is a key expression: ``derl/...`` is used as is, anything else is relative to
the run, ``fitness`` meaning ``derl/<run>/fitness/**``.
"""

from __future__ import annotations

import json
import logging
import statistics
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from contextlib import suppress
from itertools import pairwise

import msgpack
import zenoh

from derl.messages import InvalidKey, KeySpace, MessageBase, RunStatus, parse
from derl.messages.keys import ROOT
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.tools.logs import json_data, json_form, summarise_bytes

log = logging.getLogger("derl.topic")

RING = 256
"""Samples a watcher may fall behind by before the oldest are dropped."""
DISCOVERY_S = 2.0
"""How long to look for runs: the coordinator publishes its status every second."""
ASK_S = 2.0
"""How long to wait for the answers to a query (`ask`)."""


class Tap:
    """A subscription that never slows the bus: `on_sample(sample, arrival)` runs on a thread.

    `arrival` is `time.monotonic()` when the sample was taken from the ring. What `on_sample`
    raises is logged; the tap goes on.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        on_sample: Callable[[zenoh.Sample, float], None],
        capacity: int = RING,
    ) -> None:
        self.key_expr = key_expr
        self._ring = session.declare_subscriber(key_expr, zenoh.handlers.RingChannel(capacity))
        self._thread = threading.Thread(
            target=self._pump, args=(on_sample,), name=f"tap {key_expr}", daemon=True
        )
        self._thread.start()

    def _pump(self, on_sample: Callable[[zenoh.Sample, float], None]) -> None:
        while True:
            try:
                sample = self._ring.recv()
            except zenoh.ZError:  # the session closed
                return
            try:
                on_sample(sample, time.monotonic())
            except Exception:
                log.exception("%s: a sample on %s was not handled", self.key_expr, sample.key_expr)

    def join(self, timeout: float = 5.0) -> None:
        """Wait for the thread, which ends once the session is closed."""
        self._thread.join(timeout)


class Checker:
    """`Bus.check` for samples of any run (one `Bus` per run seen); rejections are counted."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self._buses: dict[str, Bus] = {}
        self._bad_keys = 0

    def check(self, key: str, payload: bytes) -> MessageBase | None:
        try:
            run = parse(key).run
        except InvalidKey as error:
            self._bad_keys += 1
            log.warning("rejected (bad key) %s", error)
            return None
        bus = self._buses.get(run) or self._buses.setdefault(run, Bus(self.session, run))
        return bus.check(payload, key)

    @property
    def rejected(self) -> Counter[str]:
        total: Counter[str] = Counter({"bad key": self._bad_keys} if self._bad_keys else {})
        for bus in self._buses.values():
            total.update(bus.rejected)
        return total


def live_runs(session: zenoh.Session, seconds: float = DISCOVERY_S) -> dict[str, RunStatus | None]:
    """Runs with a node holding a liveliness token or a coordinator publishing its status."""
    deadline = time.monotonic() + seconds
    ring = session.declare_subscriber(f"{ROOT}/*/status", zenoh.handlers.RingChannel(RING))
    found: dict[str, RunStatus | None] = {}
    try:
        for reply in session.liveliness().get(f"{ROOT}/*/alive/**", timeout=seconds):
            if reply.ok is not None:
                with suppress(InvalidKey):
                    found.setdefault(parse(str(reply.ok.key_expr)).run, None)
        time.sleep(max(0.0, deadline - time.monotonic()))
        checker = Checker(session)
        while (sample := ring.try_recv()) is not None:
            message = checker.check(str(sample.key_expr), sample.payload.to_bytes())
            if isinstance(message, RunStatus):
                found[message.run] = message
    finally:
        ring.undeclare()
    return found


def ask(
    session: zenoh.Session,
    key_expr: str,
    on_sample: Callable[[zenoh.Sample, float], None],
    timeout: float = ASK_S,
) -> int:
    """Hand `on_sample(sample, arrival)` what the run's queryables hold on `key_expr`: the
    coordinator answers ``births/*`` with the births it remembers (those before a watcher came,
    and any that went by unheard). How many samples they answered with."""
    answered = 0
    for reply in session.get(key_expr, timeout=timeout):
        if reply.ok is not None:
            answered += 1
            on_sample(reply.ok, time.monotonic())
    return answered


class RunNotFound(LookupError):
    """Several runs on the bus and no --run given; the text lists them."""


class NothingHeard(LookupError):
    """Nothing was heard of what a tool listened for; the text says what that was."""


def choose_run(session: zenoh.Session, run: str | None, patience: float = DISCOVERY_S) -> str:
    """`run`, or the only run found on the bus, looked for again while none is found, for up to
    `patience` seconds."""
    if run:
        return KeySpace(run).run
    end = time.monotonic() + patience
    runs = live_runs(session, min(DISCOVERY_S, patience))
    while not runs and (left := end - time.monotonic()) > 0:
        runs = live_runs(session, min(DISCOVERY_S, left))
    if len(runs) == 1:
        return next(iter(runs))
    if not runs:
        raise NothingHeard(f"no run heard in {patience:g} s (no derl/*/status, no live node)")
    lines = [
        f"  {name}: " + (f"{s.born}/{s.target} born" if s else "nodes alive, no status yet")
        for name, s in sorted(runs.items())
    ]
    raise RunNotFound(f"{len(runs)} runs on the bus; choose one with --run:\n" + "\n".join(lines))


def is_relative(key: str) -> bool:
    """Whether a KEY argument needs a run (it does not start with ``derl/``)."""
    return key != ROOT and not key.startswith(f"{ROOT}/")


def key_expression(key: str, run: str | None = None) -> str:
    """The key expression of a KEY argument (`run` is needed for a relative one)."""
    expr = key
    if is_relative(key):
        expr = f"{KeySpace(run or '').prefix}/{key.strip('/')}"
        expr += "" if expr.endswith("**") else "/**"
    try:
        zenoh.KeyExpr(expr)
    except zenoh.ZError as error:
        reason = str(error).split(" at /")[0]  # without the Rust source location
        raise InvalidKey(f"{key!r} is not a key expression: {reason}") from None
    return expr


def resolve(session: zenoh.Session, key: str, run: str | None) -> str:
    """A KEY argument as a key expression, finding the run on the bus if it needs one."""
    return key_expression(key, choose_run(session, run) if is_relative(key) else None)


# --- the verbs -------------------------------------------------------------------------------


def topic_list(
    options: ZenohOptions, key: str, run: str | None, duration: float, stop: threading.Event
) -> int:
    """Print the keys heard on `key` within `duration`, with message type and count; the
    number of keys."""
    seen: dict[str, Counter[str]] = {}
    with open_session(options) as session:
        checker = Checker(session)

        def on_sample(sample: zenoh.Sample, _: float) -> None:
            name = str(sample.key_expr)
            message = checker.check(name, sample.payload.to_bytes())
            seen.setdefault(name, Counter())["rejected" if message is None else message.type] += 1

        tap = Tap(session, resolve(session, key, run), on_sample)
        stop.wait(duration)
    tap.join()
    width = max((len(name) for name in seen), default=0)
    for name, types in sorted(seen.items()):
        for kind, count in types.most_common():
            print(f"{name:<{width}}  {kind:<18} {count:>7}  {count / duration:8.2f}/s")
    return len(seen)


def echo(
    options: ZenohOptions,
    key: str,
    run: str | None,
    count: int | None,
    duration: float | None,
    raw: bool,
    stop: threading.Event,
) -> int:
    """Print each message on `key` as one JSON line (bytes as {"bytes": n}); the number shown.

    `raw` shows every sample as received, valid or not: its key, size and msgpack content.
    """
    shown = 0
    with open_session(options) as session:
        checker = Checker(session)

        def on_sample(sample: zenoh.Sample, _: float) -> None:
            nonlocal shown
            if stop.is_set():
                return
            payload = sample.payload.to_bytes()
            if raw:
                line = _raw_form(str(sample.key_expr), payload)
            else:
                message = checker.check(str(sample.key_expr), payload)
                if message is None:
                    return
                line = json_form(message, summarise_bytes)
            try:
                print(json.dumps(line), flush=True)
            except OSError:  # the reader went away (e.g. `| head`)
                stop.set()
                return
            shown += 1
            if count is not None and shown >= count:
                stop.set()

        tap = Tap(session, resolve(session, key, run), on_sample)
        stop.wait(duration)
    tap.join()
    return shown


def _raw_form(key: str, payload: bytes) -> dict[str, object]:
    try:
        content = msgpack.unpackb(payload, strict_map_key=False)
    except Exception as error:  # any garbage
        return {"key": key, "bytes": len(payload), "error": f"not msgpack: {error!r}"}
    return {"key": key, "bytes": len(payload), "msgpack": json_data(content, summarise_bytes)}


def hz(
    options: ZenohOptions,
    key: str,
    run: str | None,
    duration: float,
    window: int,
    stop: threading.Event,
) -> int:
    """Print, every second, the rate of samples on `key` (like `ros2 topic hz`); the number of
    samples heard."""
    arrivals: deque[float] = deque(maxlen=window + 1)
    heard = 0

    def arrived(_: zenoh.Sample, at: float) -> None:
        nonlocal heard
        heard += 1
        arrivals.append(at)

    with open_session(options) as session:
        tap = Tap(session, resolve(session, key, run), arrived)
        end = time.monotonic() + duration
        while not stop.wait(min(1.0, max(0.0, end - time.monotonic()))):
            print(rate_line(tuple(arrivals)), flush=True)
            if time.monotonic() >= end:
                break
    tap.join()
    return heard


def rate_line(arrivals: tuple[float, ...]) -> str:
    """Average rate, min/max/std of the intervals between `arrivals` (seconds)."""
    if len(arrivals) < 2:
        return "no new messages"
    gaps = [b - a for a, b in pairwise(arrivals)]
    mean = statistics.fmean(gaps)
    return (
        f"average rate: {1 / mean if mean else float('inf'):.3f} Hz  min: {min(gaps):.4f} s  "
        f"max: {max(gaps):.4f} s  std dev: {statistics.pstdev(gaps):.5f} s  window: {len(gaps)}"
    )
