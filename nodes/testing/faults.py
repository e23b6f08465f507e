"""Faults a test or the soak puts on a run's bus: malformed payloads on a key of every kind, and
a liveliness token outside the key space."""

from __future__ import annotations

import msgpack
import zenoh

from derl.messages import RunStatus, encode
from derl.messages.examples import examples
from derl.messages.keys import ARITY
from derl.nodes.runtime.bus import Bus


def put_garbage(bus: Bus) -> tuple[int, zenoh.LivelinessToken]:
    """Malformed payloads on a key of every kind (ids of trainer a where a node goes), and a
    liveliness token outside the key space: the number of payloads put, and the token."""
    status = next(m for m in examples(bus.run, 0) if isinstance(m, RunStatus))
    payloads = (
        b"\xff\x00garbage",
        msgpack.packb({**status.model_dump(), "schema_version": 99}),
        msgpack.packb([1, 2]),
        encode(status),  # a valid message of the wrong type (on every key but its own)
    )
    for kind, arity in ARITY.items():
        parts = ("trainer", "a") if kind == "alive" else ("a", "x", "x")[:arity]
        for payload in payloads if kind != "status" else payloads[:3]:
            bus.session.put(bus.keys.key(kind, *parts), payload)
    stray = bus.session.liveliness().declare_token(f"derl/{bus.run}/alive/trainer/b@d")
    return len(ARITY) * len(payloads) - 1, stray
