"""The paper's actor-critic: separate actor and critic encoders, a diagonal Gaussian, a value head.

Each encoder runs one [dim -> 64 -> 64] tanh MLP per observation type, concatenates their outputs
and passes them through a 64-unit tanh layer (also with a single type, so every body and task uses
one code path). This module defines and initialises the network and acts for `Policy`; training
runs its arithmetic by hand on a flat copy of the weights (`derl.rl.fused`).
"""

from __future__ import annotations

import torch
from torch import nn

HIDDEN = 64
"""Width of every hidden layer (paper, appendix B)."""

TensorObs = dict[str, torch.Tensor]


class Encoder(nn.Module):
    """Per-type two-layer tanh MLPs, concatenated, then one more tanh layer."""

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
        self.fuse = nn.Sequential(nn.Linear(HIDDEN * len(self.keys), HIDDEN), nn.Tanh())

    def forward(self, obs: TensorObs) -> torch.Tensor:
        return self.fuse(torch.cat([self.branches[key](obs[key]) for key in self.keys], dim=-1))


class ActorCritic(nn.Module):
    """Separate actor and critic; Gaussian policy with a state-independent learned log-std."""

    def __init__(self, obs_spaces: dict[str, int], action_dim: int) -> None:
        super().__init__()
        self.obs_spaces = dict(obs_spaces)
        self.action_dim = action_dim
        self.actor = Encoder(obs_spaces)
        self.critic = Encoder(obs_spaces)
        self.mean_head = nn.Linear(HIDDEN, action_dim)
        self.value_head = nn.Linear(HIDDEN, 1)
        self.log_std = nn.Parameter(torch.zeros(action_dim))
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.orthogonal_(module.weight, gain=1.0)
                nn.init.zeros_(module.bias)

    def action_mean(self, obs: TensorObs) -> torch.Tensor:
        """(B, A) mean of the action distribution (the deterministic action)."""
        return self.mean_head(self.actor(obs))

    def value(self, obs: TensorObs) -> torch.Tensor:
        """(B,) state value."""
        return self.value_head(self.critic(obs)).squeeze(-1)
