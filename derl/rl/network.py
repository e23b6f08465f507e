"""The paper's actor-critic: separate actor and critic encoders, a diagonal Gaussian, a value head.

Each encoder runs one [dim -> 64 -> 64] tanh MLP per observation type; with several types it
concatenates their outputs and passes them through a 64-unit tanh layer, with one type (FT and the
flat test tasks: proprioception only) that MLP's output is the encoding (the released code's
`ConcatMLPEncoder` and `MLPObsEncoder`); `derl.rl.architecture` lists its parameters' names and
shapes without torch. This module defines and initialises the network and acts
for `Policy`; training minimises the PPO loss (`derl.rl.loss`) running the network's arithmetic
by hand on a flat copy of the weights (`derl.rl.fused`).
"""

from __future__ import annotations

import torch
from torch import nn

from derl.rl.architecture import HIDDEN

TensorObs = dict[str, torch.Tensor]


class Encoder(nn.Module):
    """Per-type two-layer tanh MLPs; several are concatenated and pass one more tanh layer
    (`fuse`, None with a single type)."""

    def __init__(self, obs_spaces: dict[str, int]) -> None:
        super().__init__()
        self.keys = sorted(obs_spaces)
        self.branches = nn.ModuleDict(
            {
                key: nn.Sequential(
                    nn.Linear(obs_spaces[key], HIDDEN),
                    nn.Tanh(),
                    nn.Linear(HIDDEN, HIDDEN),
                    nn.Tanh(),
                )
                for key in self.keys
            }
        )
        self.fuse = (
            nn.Sequential(nn.Linear(HIDDEN * len(self.keys), HIDDEN), nn.Tanh())
            if len(self.keys) > 1
            else None
        )

    def forward(self, obs: TensorObs) -> torch.Tensor:
        encoded = [self.branches[key](obs[key]) for key in self.keys]
        return encoded[0] if self.fuse is None else self.fuse(torch.cat(encoded, dim=-1))


class ActorCritic(nn.Module):
    """Separate actor and critic; Gaussian policy with a state-independent learned log-std."""

    def __init__(
        self, obs_spaces: dict[str, int], action_dim: int, initialize: bool = True
    ) -> None:
        """`initialize`: draw the initial weights (orthogonal); False for a network whose weights
        are loaded next (a checkpoint's), which skips the QR decompositions (most of its cost)."""
        super().__init__()
        self.obs_spaces = dict(obs_spaces)
        self.action_dim = action_dim
        self.actor = Encoder(obs_spaces)
        self.critic = Encoder(obs_spaces)
        self.mean_head = nn.Linear(HIDDEN, action_dim)
        self.value_head = nn.Linear(HIDDEN, 1)
        self.log_std = nn.Parameter(torch.zeros(action_dim))
        for module in self.modules() if initialize else ():
            if isinstance(module, nn.Linear):
                nn.init.orthogonal_(module.weight, gain=1.0)
                nn.init.zeros_(module.bias)

    def action_mean(self, obs: TensorObs) -> torch.Tensor:
        """(B, A) mean of the action distribution (the deterministic action)."""
        return self.mean_head(self.actor(obs))

    def value(self, obs: TensorObs) -> torch.Tensor:
        """(B,) state value."""
        return self.value_head(self.critic(obs)).squeeze(-1)
