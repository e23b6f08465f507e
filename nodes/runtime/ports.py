"""Free ports to listen on, drawn outside the kernel's ephemeral range: a port free when drawn
and listened on a moment later by another process (`derl run --port 0`, a test's endpoint) is
then never taken meanwhile by a socket bound to port 0 or by an outgoing connection, which the
kernel gives ports of that range only."""

from __future__ import annotations

import random
import socket
from pathlib import Path

EPHEMERAL = Path("/proc/sys/net/ipv4/ip_local_port_range")
LINUX_EPHEMERAL = (32768, 60999)  # the kernel's default, where /proc does not say
LOWEST = 10_000  # below: the ports of well-known services
TRIES = 500


def ephemeral_range() -> tuple[int, int]:
    """The kernel's ephemeral ports (first, last)."""
    try:
        first, last = (int(n) for n in EPHEMERAL.read_text().split())
    except (OSError, ValueError):
        return LINUX_EPHEMERAL
    return first, last


def bind_error(host: str, port: int) -> OSError | None:
    """Why a listener may not bind `port` on `host` now (with SO_REUSEADDR, as Zenoh's), or
    None where it may."""
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as error:
            return error
    return None


def bindable(host: str, port: int) -> bool:
    """Whether a listener may bind `port` on `host` now."""
    return bind_error(host, port) is None


def free_port(host: str = "127.0.0.1", span: int = 1) -> int:
    """A port P such that P .. P + span - 1 can be bound on `host` now, drawn at random outside
    the ephemeral range (a small race remains with another process drawing the same)."""
    first, last = ephemeral_range()
    ranges = [(low, high - span) for low, high in ((LOWEST, first), (last + 1, 65536))
              if high - span > low]  # fmt: skip
    draw = random.Random()
    for _ in range(TRIES if ranges else 0):
        low, high = draw.choice(ranges)
        port = draw.randrange(low, high)
        if all(bindable(host, port + k) for k in range(span)):
            return port
    raise OSError(f"no {span} free consecutive ports on {host} outside the ephemeral range")
