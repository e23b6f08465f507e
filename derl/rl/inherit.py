"""A child's controller started from its parent's trained one (`inherit: parent`, Lamarckian).

The two bodies differ by one mutation, so most of their parts are the same: the parts are matched
by name (the genome's limb ids name the joints, actuators and sensors: `Layout`, from
`derl.envs.UnimalEnv`'s `proprioception_labels` and `action_labels`). Of the network, every
weight of a shared part is the parent's: the first layer's input columns of the proprioception
columns both bodies have, the action head's rows and the log-std of the actuators both have, and
every layer whose shape does not depend on the body (the hidden layers, the fusion, the value
head, the other observation types' first layers, same in one world); a part only the child has
keeps the fresh weights the training drew from its seed. The observation normaliser goes on from
the parent's: its mean and variance of the shared columns and its count (the inherited weights
see their inputs scaled as they were trained), a new column at the fresh normaliser's mean 0 and
variance 1. The optimiser (Adam's moments) and the reward scaler start fresh: a checkpoint keeps
neither, and the child's rewards are its own. Same inputs, same bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from derl.rl.checkpoint import Checkpoint
from derl.rl.network import ActorCritic
from derl.rl.normalize import NORMALIZED, ObsNormalizer

FIRST_LAYER = f"branches.{NORMALIZED}.0.weight"
"""Suffix of an encoder's first layer over the proprioception (one column per input)."""
PER_ACTION = ("mean_head.weight", "mean_head.bias", "log_std")
"""Parameters whose first axis is the actions."""


@dataclass(frozen=True)
class Layout:
    """What each proprioception column and each action of a body is (a name per part)."""

    proprioception: tuple[str, ...]
    actions: tuple[str, ...]


@dataclass(frozen=True)
class Inheritance:
    """The parent's trained controller and both bodies' layouts; called on the child's fresh
    network and normaliser (`derl.rl.ppo.train`'s `initial`), it puts the parent's in."""

    parent: Checkpoint
    parent_layout: Layout
    child_layout: Layout

    def __post_init__(self) -> None:
        size = self.parent.obs_spaces.get(NORMALIZED)
        if size != len(self.parent_layout.proprioception):
            raise ValueError(
                f"the parent's checkpoint has {size} proprioception inputs, its body "
                f"{len(self.parent_layout.proprioception)}: not this body's checkpoint"
            )
        if self.parent.action_dim != len(self.parent_layout.actions):
            raise ValueError(
                f"the parent's checkpoint has {self.parent.action_dim} actions, its body "
                f"{len(self.parent_layout.actions)}: not this body's checkpoint"
            )

    def __call__(self, net: ActorCritic, obs_norm: ObsNormalizer) -> None:
        columns = _matches(self.child_layout.proprioception, self.parent_layout.proprioception)
        actions = _matches(self.child_layout.actions, self.parent_layout.actions)
        weights = net.state_dict()
        for name, fresh in weights.items():
            old = self.parent.weights.get(name)
            if old is None:
                continue  # a layer the parent's network has not (another number of types)
            if name.endswith(FIRST_LAYER):
                fresh[:, columns[0]] = old[:, columns[1]]
            elif name in PER_ACTION:
                fresh[actions[0]] = old[actions[1]]
            elif fresh.shape == old.shape:
                fresh.copy_(old)
        net.load_state_dict(weights)
        _inherit_statistics(obs_norm, self.parent.obs_stats, columns)


def _matches(child: tuple[str, ...], parent: tuple[str, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices of the child's names that the parent has, and of the same names in the parent's."""
    where = {name: i for i, name in enumerate(parent)}
    pairs = [(i, where[name]) for i, name in enumerate(child) if name in where]
    mine, theirs = zip(*pairs, strict=True) if pairs else ((), ())
    return torch.tensor(mine, dtype=torch.long), torch.tensor(theirs, dtype=torch.long)


def _inherit_statistics(
    obs_norm: ObsNormalizer, parent: dict[str, np.ndarray], columns: tuple[torch.Tensor, ...]
) -> None:
    """The parent's mean and variance of the shared proprioception columns, and its count."""
    state = obs_norm.state_dict()
    mine, theirs = columns[0].numpy(), columns[1].numpy()
    for stat in ("mean", "var"):
        key = f"{NORMALIZED}/{stat}"
        state[key][mine] = parent[key][theirs]
    state[f"{NORMALIZED}/count"] = parent[f"{NORMALIZED}/count"]
    obs_norm.load_state_dict(state)
