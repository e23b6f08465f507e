"""A run's fingerprint: one short hash of its births, so two researchers compare runs in a line.

A run is a function of its profile and seed (`derl.evolution.evolution`): whatever the number of
trainers, their speed or what crashed, the same children are born of the same parents with the
same bodies and the same fitness to the bit. The fingerprint hashes exactly that, each birth as
(child, parent, generation, the fitness's bits, `body_hash` of the body), in child order
(`child_order`: the order children are bred, not the order their trainings finished), and the
identity of every plugin the run used (name, version, source hash): the same births from other
code are another run.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable

from derl.unimal import Genome, body_hash

BirthFacts = tuple[str, str | None, int, float, Genome]
"""A birth as the fingerprint sees it: child, parent, generation, fitness, body."""


def child_order(name: str) -> tuple[bool, int]:
    """A child's place in the order children are bred: the initial bodies (i0000, i0001, ...)
    first, then the tournaments' children (c00000, ...)."""
    return name.startswith("c"), int(name[1:])


def fingerprint(births: Iterable[BirthFacts], plugins: Iterable[str] = ()) -> str:
    """16 hex digits of SHA-256 over the births in child order (equal runs, equal prints), after
    the identities of the run's plugins (`derl.plugins.Plugin`, as JSON; a run without any hashes
    its births alone)."""
    digest = hashlib.sha256()
    for plugin in plugins:
        digest.update(f"plugin {plugin}\n".encode())
    for child, parent, generation, fitness, genome in sorted(
        births, key=lambda b: child_order(b[0])
    ):
        line = f"{child} {parent} {generation} {float(fitness).hex()} {body_hash(genome)}\n"
        digest.update(line.encode())
    return digest.hexdigest()[:16]
