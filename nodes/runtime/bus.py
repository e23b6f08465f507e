"""The Zenoh side of every node: a session configured from flags, typed publish and subscribe.

Defaults follow measurements (docs/bus.md): multicast scouting OFF (only explicit
endpoints), shared memory OFF (with Zenoh's default, a node kept memory for every session that
ever came), a 2.5 s transport lease (a hung node is declared dead 2.5 s after it stops), control
messages sent with `CongestionControl.BLOCK` (the default DROP loses bursts even on loopback),
monitors subscribing through a `RingChannel` so a slow viewer can never stall a trainer. A
``--zenoh-config`` file (TLS, access control, anything Zenoh accepts) is the base; flags given on
the command line override it, multicast stays off unless ``--multicast`` is given, and shared
memory stays off.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import queue
import re
import socket
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final, Literal, TypeVar, cast, overload

import zenoh
from pydantic import BaseModel, ConfigDict, Field

from derl.messages import DecodeError, InvalidKey, KeySpace, MessageBase, decode, encode, parse
from derl.messages.types import MAX_MESSAGE_BYTES

log = logging.getLogger("derl.bus")
M = TypeVar("M", bound=MessageBase)  # a message type `Bus.subscribe` hands its handler

LEASE_MS = 2500
# A peer must listen somewhere for the others to mesh with it (gossip tells them where): by
# default an ephemeral loopback port; across hosts, give --listen with a routable address.
LOOPBACK_ANY_PORT = ("tcp/127.0.0.1:0",)
MSGPACK = zenoh.Encoding("application/msgpack")
INLET_CAPACITY = 1 << 16  # samples an `Inlet` holds (allocated as they come); when full, the
# oldest are dropped: a worker sends its asks and results again until answered (a lost JobFailed's
# job comes back when its lease runs out), and a flood must not fill the coordinator (docs/bus.md)


DROPPABLE: Final = frozenset({"TrainProgress", "PopulationSnapshot", "RunStatus"})
"""Periodic message types, each replaced by the next: dropped rather than waited for when the
link is congested. Every other type is control plane and never dropped."""


@functools.cache
def _encoding(message_type: str) -> zenoh.Encoding:
    """msgpack with the message's type as its schema (one object per type)."""
    return MSGPACK.with_schema(message_type)


def congestion_control(message_type: str) -> zenoh.CongestionControl:
    """DROP for a `DROPPABLE` type, else BLOCK."""
    if message_type in DROPPABLE:
        return zenoh.CongestionControl.DROP
    return zenoh.CongestionControl.BLOCK


class ZenohOptions(BaseModel):
    """How a node joins the bus."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast: bool = False
    lease_ms: int = Field(LEASE_MS, ge=100)
    config_file: Path | None = None


def zenoh_config(options: ZenohOptions) -> zenoh.Config:
    """The Zenoh config of `options` (unknown keys in a config file are Zenoh's errors)."""
    config = zenoh.Config()
    if options.config_file:
        try:
            config = zenoh.Config.from_file(str(options.config_file))
        except zenoh.ZError as error:  # Zenoh's reason does not name the file
            raise zenoh.ZError(f"--zenoh-config {options.config_file}: {error}") from None

    def put(key: str, value: object) -> None:
        config.insert_json5(key, json.dumps(value))

    put("mode", options.mode)
    if options.listen or not options.config_file:
        listen = options.listen or (LOOPBACK_ANY_PORT if options.mode == "peer" else ())
        put("listen/endpoints", list(listen))
    if options.connect or not options.config_file:
        put("connect/endpoints", list(options.connect))
    put("scouting/multicast/enabled", options.multicast)
    # derl sends no shared-memory buffers, and with Zenoh's shared memory on, a router or peer
    # kept ~19 MB for every same-host session that ever sent it large samples (docs/bus.md)
    put("transport/shared_memory/enabled", False)
    # a larger sample than any derl message is dropped before it is assembled (Zenoh's default
    # 1 GiB let a 50 MB one raise a router's memory for good)
    put("transport/link/rx/max_message_size", MAX_MESSAGE_BYTES)
    put("transport/link/tx/lease", options.lease_ms)
    if options.mode == "client":
        put("connect/timeout_ms", 30_000)  # wait for a router that starts a little later
    return config


def node_name(role: str, index: int = 0) -> str:
    """A node id unique on the network: role, host, process and index, as a safe key segment."""
    host = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname())[:64] or "host"
    return f"{role}-{host}-{os.getpid()}-{index}"


class Bus:
    """Typed messages over one Zenoh session for one run; counts what it had to reject."""

    def __init__(
        self,
        session: zenoh.Session,
        run: str,
        on_reject: Callable[[str, str, MessageBase | None], None] | None = None,
    ) -> None:
        """`on_reject(why, key, message or None)` hears of every sample the check refuses."""
        self.session = session
        self.on_reject = on_reject
        self.keys = KeySpace(run)
        self.run = run
        self.rejected: Counter[str] = Counter()
        self._subscribers: list[zenoh.Subscriber] = []

    def publish(self, msg: MessageBase, data: bytes | None = None) -> None:
        """Publish on the message's own key with its type's `congestion_control`. `data` is the
        message's encoding, if the caller has it already."""
        self.session.put(
            self.keys.key_for(msg),
            encode(msg) if data is None else data,
            encoding=_encoding(msg.type),
            congestion_control=congestion_control(msg.type),
        )

    @overload
    def subscribe(self, key_expr: str, handler: Callable[[MessageBase], None]) -> None: ...

    @overload
    def subscribe(
        self, key_expr: str, handler: Callable[[M], None], kinds: tuple[type[M], ...]
    ) -> None: ...

    def subscribe(
        self,
        key_expr: str,
        handler: Callable[[Any], None],
        kinds: tuple[type[MessageBase], ...] = (),
    ) -> None:
        """Decode every sample on `key_expr` and hand valid messages of this run (and of the
        given types, if any) to `handler`; log and count the rest."""

        def on_sample(sample: zenoh.Sample) -> None:
            message = self.check(sample.payload.to_bytes(), str(sample.key_expr), kinds)
            if message is not None:
                handler(message)

        self._subscribers.append(self.session.declare_subscriber(key_expr, on_sample))

    def inbox(self, key_expr: str, kinds: tuple[type[MessageBase], ...] = ()) -> queue.Queue:
        """A queue that receives the valid messages on `key_expr`."""
        box: queue.Queue[MessageBase] = queue.Queue()
        self.subscribe(key_expr, box.put, kinds)
        return box

    def inlet(
        self,
        key_expr: str,
        kinds: tuple[type[MessageBase], ...] = (),
        capacity: int = INLET_CAPACITY,
        clock: Callable[[], float] = time.monotonic,
    ) -> Inlet:
        """The valid messages on `key_expr`, queued by Zenoh (up to `capacity`, then the oldest
        dropped: a `RingChannel`, which never stalls the session) and decoded by the thread that
        takes them (`Inlet.take`); `clock` times `Inlet.arrived_after`."""
        subscriber = self.session.declare_subscriber(key_expr, zenoh.handlers.RingChannel(capacity))
        self._subscribers.append(subscriber)
        return Inlet(self, subscriber, kinds, clock)

    def check(
        self, payload: bytes, key: str, kinds: tuple[type[MessageBase], ...] = ()
    ) -> MessageBase | None:
        """The message in a payload received on `key`, or None (logged and counted)."""
        try:
            message = decode(payload)
        except DecodeError as error:
            self._reject("malformed", key, f"{error}")
            return None
        if message.run != self.run:
            self._reject("other run", key, f"message of run {message.run!r}", message)
            return None
        if kinds and not isinstance(message, kinds):
            self._reject("unexpected type", key, f"unexpected {message.type}", message)
            return None
        if self.keys.key_for(message) != key:
            # every sender's node id is part of its keys: a message naming another node is
            # refused here, so with access control one node cannot speak for another
            detail = f"a {message.type} belongs on {self.keys.key_for(message)}"
            self._reject("wrong key", key, detail, message)
            return None
        return message

    def _reject(self, why: str, key: str, detail: str, message: MessageBase | None = None) -> None:
        self.rejected[why] += 1
        log.warning("rejected (%s) %s: %s", why, key, detail[:300])
        if self.on_reject is not None:
            self.on_reject(why, key, message)

    def token(self, role: str, node: str) -> zenoh.LivelinessToken:
        """Announce this node alive until the session closes or the process dies."""
        return self.session.liveliness().declare_token(self.keys.alive(role, node))

    def watch_alive(self, handler: Callable[[str, str, bool], None]) -> None:
        """Call `handler(role, node, alive)` for every token of this run, existing ones too."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                role, node = parse(str(sample.key_expr)).parts
            except InvalidKey as error:
                log.warning("ignored liveliness token %s: %s", sample.key_expr, error)
                return
            handler(role, node, sample.kind == zenoh.SampleKind.PUT)

        self._subscribers.append(
            self.session.liveliness().declare_subscriber(
                self.keys.all("alive"), on_sample, history=True
            )
        )


class Inlet:
    """Samples of one subscription, held in Zenoh's own queue until taken: no Python callback
    thread, so a busy single-threaded reader (the coordinator) does not hand the interpreter
    lock to a callback for every sample (measured: each hand-over costs more than decoding).

    `arrived_after` bounds how long the last `take`'s messages waited: each came in after that
    moment (on `clock`), when the queue was last seen empty. Under a backlog it lies seconds
    back; otherwise it is the previous take's."""

    def __init__(
        self,
        bus: Bus,
        subscriber: zenoh.Subscriber,
        kinds: tuple[type[MessageBase], ...],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.bus, self.subscriber, self.kinds, self.clock = bus, subscriber, kinds, clock
        self.empty_at = self.arrived_after = clock()

    def take(self, limit: int) -> list[MessageBase]:
        """Up to `limit` valid messages that are waiting (checked as `Bus.check`), oldest first."""
        self.arrived_after = self.empty_at
        taken: list[MessageBase] = []
        for _ in range(limit):
            sample = self.subscriber.try_recv()
            if sample is None:
                self.empty_at = self.clock()
                break
            message = self.bus.check(sample.payload.to_bytes(), str(sample.key_expr), self.kinds)
            if message is not None:
                taken.append(message)
        return taken


def open_session(options: ZenohOptions) -> zenoh.Session:
    """Open a Zenoh session; use it as a context manager (an open session blocks exit)."""
    return zenoh.open(zenoh_config(options))


def matched(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches `publisher`'s key now (its `matching_status`, which zenoh's
    stubs call a bool, is a `zenoh.MatchingStatus`)."""
    return cast(zenoh.MatchingStatus, publisher.matching_status).matching
