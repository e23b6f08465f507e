"""derl's extension points in one table (`REGISTRIES`: a plugin's kind to its registry), and the
checks a profile's plugins pass before any node starts (`check_profile_plugins`).

The kinds: ``task`` (`derl.envs.registry.TASK_REGISTRY`, entry point group ``derl.tasks``),
``selection`` (`derl.evolution.selection.SELECTION_REGISTRY`, ``derl.selection``) and
``operator`` (`derl.unimal.mutations.OPERATOR_REGISTRY`, ``derl.operators``). docs/extending.md
says how to write each.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from derl.envs.registry import TASK_REGISTRY, make_task
from derl.evolution.config import EvolutionConfig
from derl.evolution.evolution import tournament_draws
from derl.evolution.member import Member
from derl.evolution.selection import SELECTION_REGISTRY, Draws, make_selection, select
from derl.plugins import PluginError, Registry
from derl.unimal.genome import Genome
from derl.unimal.mutations import MAX_ATTEMPTS, OPERATOR_REGISTRY, MutationFailed, mutate
from derl.unimal.sampling import random_genome

REGISTRIES: Mapping[str, Registry[Any]] = {
    "task": TASK_REGISTRY,
    "selection": SELECTION_REGISTRY,
    "operator": OPERATOR_REGISTRY,
}
"""Every extension point by the kind a `derl.plugins.Plugin` names."""


def check_profile_plugins(config: EvolutionConfig, bodies: int = 3) -> None:
    """Try the plugins `config` names once, so that one that cannot work stops a run before any
    node starts (`PluginError` naming it): each plugin task is made, the selection scheme chooses
    from a made-up pool, and each plugin operator must make a valid child of one of `bodies`
    bodies drawn from the run's seed."""
    plugins = {(plugin.kind, plugin.name) for plugin in config.plugins()}
    for kind, name in plugins:
        if kind == "task":
            make_task(name)
    if ("selection", config.selection) in plugins:
        scheme = make_selection(config.selection, config.selection_options)
        pool = [
            Member(f"i{k:04d}", float(k % 7), None, k, cost_of_work=1.0 + k % 3)
            for k in range(config.population)
        ]
        positions, _ = tournament_draws(config.seed, 0, config.tournament, len(pool))
        select(config.selection, scheme, pool, Draws(tuple(positions), config.seed, 0))
    operators = [name for kind, name in plugins if kind == "operator"]
    if operators:
        rng = np.random.default_rng([config.seed, 2])
        drawn = [random_genome(rng) for _ in range(bodies)]
        for op in sorted(operators):
            _made_a_child(op, drawn, config.mutations)


def _made_a_child(op: str, bodies: list[Genome], weights: dict[str, float] | None) -> None:
    reasons = []
    for k, body in enumerate(bodies):
        try:
            mutate(body, np.random.default_rng(k), op=op, weights=weights)
            return
        except MutationFailed as failure:
            reasons.append(failure.reason)
    raise PluginError(
        f"operator {op!r} made no valid child of {len(bodies)} bodies "
        f"({MAX_ATTEMPTS} attempts each); last: {reasons[-1] if reasons else 'it never applies'}"
    )
