"""The key expressions of the bus (docs/architecture.md), built and parsed in one place.

Every key is ``derl/<run>/<kind>/<id>...`` with a fixed number of id segments per kind. Ids must
be safe key segments (`messages.types.ID_PATTERN`), so a built key never holds a wildcard or an
empty chunk. `KeySpace.key_for` routes a message to its key; `parse` takes a received key apart.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from typing import Final, NamedTuple

from derl.messages.schema import MessageBase
from derl.messages.types import ID_PATTERN

ROOT: Final = "derl"

ARITY: Final[dict[str, int]] = {
    "alive": 2,
    "ready": 1,
    "job": 1,
    "tournament": 1,
    "progress": 2,
    "fitness": 2,
    "failure": 2,
    "ack": 1,
    "eval": 3,
    "births": 1,
    "checkpoint": 1,
    "lost": 1,
    "rejected": 0,
    "settings": 0,
    "population": 0,
    "status": 0,
}
"""Key kinds and how many id segments follow each."""

REMEMBERED_BIRTHS: Final = 1000
"""How many of its latest births (and children given up) the coordinator answers a query on
``births/*`` with: a monitor that hears fewer than the run's status counts asks again until an
answer fills the gap or holds this many."""

PUBLISHERS: Final[dict[str, tuple[str, ...]]] = {
    "alive": ("trainer", "evaluator"),
    "ready": ("trainer", "evaluator"),
    "job": ("coordinator",),
    "tournament": ("coordinator",),
    "progress": ("trainer", "evaluator"),
    "fitness": ("trainer",),
    "failure": ("trainer", "evaluator"),
    "ack": ("coordinator",),
    "eval": ("evaluator",),
    "births": ("coordinator",),
    "checkpoint": ("coordinator",),
    "lost": ("coordinator",),
    "rejected": (),
    "settings": (),
    "population": ("coordinator",),
    "status": ("coordinator",),
}
"""Key kind -> the roles that publish on it (none: journaled, never published)."""

ROUTES: Final[dict[str, tuple[str, tuple[str, ...]]]] = {
    "WorkerReady": ("ready", ("node",)),
    "TrainJob": ("job", ("node",)),
    "EvalJob": ("job", ("node",)),
    "Cancel": ("job", ("node",)),
    "Tournament": ("tournament", ("agent",)),
    "TrainProgress": ("progress", ("node", "agent")),
    "FitnessReport": ("fitness", ("node", "agent")),
    "JobFailed": ("failure", ("node", "job")),
    "Ack": ("ack", ("node",)),
    "Reject": ("ack", ("node",)),
    "EvalResult": ("eval", ("node", "agent", "task")),
    "Birth": ("births", ("agent",)),
    "ChildFailed": ("births", ("agent",)),
    "Quarantine": ("births", ("agent",)),
    "Retrained": ("births", ("agent",)),
    "Undo": ("births", ("agent",)),
    "Dropped": ("births", ("agent",)),
    "JobLost": ("lost", ("node",)),
    "Rejection": ("rejected", ()),
    "RunSettings": ("settings", ()),
    "PopulationSnapshot": ("population", ()),
    "RunStatus": ("status", ()),
}
"""Message type -> its key kind and the fields that fill the id segments. Every message a
worker publishes carries its node id in its key, so access control can give each node's
certificate its own keys only, and a message whose `node` differs from its key is rejected."""


class InvalidKey(ValueError):
    """A key, or an id meant for one, that does not fit the key space."""


def check_segment(value: str) -> str:
    """`value` if it is a safe key segment, else InvalidKey."""
    if not isinstance(value, str) or not _safe(value):
        raise InvalidKey(f"{value!r} is not a safe key segment ([A-Za-z0-9_.-], 1 to 128)")
    return value


@functools.lru_cache(maxsize=1 << 14)
def _safe(value: str) -> bool:
    """Matches `ID_PATTERN` (cached: a node's or a child's name recurs in many keys)."""
    return re.fullmatch(ID_PATTERN, value) is not None


class ParsedKey(NamedTuple):
    """A received key taken apart."""

    run: str
    kind: str
    parts: tuple[str, ...]


def parse(key: str) -> ParsedKey:
    """Run, kind and id segments of a concrete key; InvalidKey for anything else."""
    root, *rest = key.split("/")
    if root != ROOT or len(rest) < 2:
        raise InvalidKey(f"{key!r} is not {ROOT}/<run>/<kind>/...")
    run, kind, *parts = rest
    KeySpace(run).key(kind, *parts)
    return ParsedKey(run, kind, tuple(parts))


def _arity(kind: str) -> int:
    try:
        return ARITY[kind]
    except KeyError:
        raise InvalidKey(f"unknown kind {kind!r}") from None


def kind_of(msg: MessageBase) -> str:
    """The key kind a message is published under."""
    return ROUTES[msg.type][0]


@dataclass(frozen=True)
class KeySpace:
    """The keys of one run."""

    run: str

    def __post_init__(self) -> None:
        check_segment(self.run)

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.run}"

    def key(self, kind: str, *parts: str) -> str:
        """The concrete key of `kind` with its id segments."""
        if len(parts) != _arity(kind):
            raise InvalidKey(f"{kind} keys have {ARITY[kind]} id segments, not {len(parts)}")
        return "/".join((self.prefix, kind, *map(check_segment, parts)))

    def alive(self, role: str, node: str) -> str:
        return self.key("alive", role, node)

    def ready(self, node: str) -> str:
        return self.key("ready", node)

    def job(self, node: str) -> str:
        return self.key("job", node)

    def tournament(self, child: str) -> str:
        return self.key("tournament", child)

    def progress(self, node: str, child: str) -> str:
        return self.key("progress", node, child)

    def fitness(self, node: str, child: str) -> str:
        return self.key("fitness", node, child)

    def births(self, child: str) -> str:
        return self.key("births", child)

    def checkpoint(self, agent: str) -> str:
        """Where the coordinator answers a query for `agent`'s checkpoint (the file's bytes)."""
        return self.key("checkpoint", agent)

    def ack(self, node: str) -> str:
        return self.key("ack", node)

    def eval(self, node: str, agent: str, task: str) -> str:
        return self.key("eval", node, agent, task)

    def population(self) -> str:
        return self.key("population")

    def status(self) -> str:
        return self.key("status")

    def all(self, kind: str, *fixed: str) -> str:
        """Subscription to every key of `kind` whose leading id segments are `fixed`.

        ``all("fitness")`` is ``derl/<run>/fitness/*/*``; ``all("alive", "trainer")`` is
        ``derl/<run>/alive/trainer/*``.
        """
        if len(fixed) > _arity(kind):
            raise InvalidKey(f"{kind} keys have {ARITY[kind]} id segments, not {len(fixed)}")
        stars = ("*",) * (ARITY[kind] - len(fixed))
        return "/".join((self.prefix, kind, *map(check_segment, fixed), *stars))

    def everything(self) -> str:
        """Subscription to all traffic of the run."""
        return f"{self.prefix}/**"

    def family(self, kind: str) -> str:
        """``derl/<run>/<kind>``: the topic of a kind's channels in an MCAP journal."""
        _arity(kind)
        return f"{self.prefix}/{kind}"

    def key_for(self, msg: MessageBase) -> str:
        """The key `msg` is published under; its run must be this one."""
        if msg.run != self.run:
            raise InvalidKey(f"a message of run {msg.run!r} in the key space of {self.run!r}")
        kind, fields = ROUTES[msg.type]
        return self.key(kind, *(getattr(msg, field) for field in fields))
