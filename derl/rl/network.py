"""The paper's actor-critic: separate actor and critic encoders, a diagonal Gaussian, a value head.

Each encoder runs one [dim -> 64 -> 64] tanh MLP per observation type, concatenates their outputs
and passes them through a 64-unit tanh layer (also with a single type, so every body and task uses
one code path). The Gaussian log-probability and entropy are written out directly: sampling uses
no `torch.distributions`, which costs more than the network itself for small batches.
"""

from __future__ import annotations

import math

import torch
from torch import nn

HIDDEN = 64
"""Width of every hidden layer (paper, appendix B)."""

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)

TensorObs = dict[str, torch.Tensor]


def gaussian_log_prob(
    actions: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor
) -> torch.Tensor:
    """Log-density of a diagonal Gaussian, summed over the last axis."""
    z = (actions - mean) * torch.exp(-log_std)
    return (-0.5 * z.square() - log_std - _HALF_LOG_2PI).sum(-1)


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    """Entropy of a diagonal Gaussian per action dimension, averaged over them (a scalar).

    The released code's `Normal(mu, std).entropy().mean()`: the mean over batch and action
    dimensions (the entropy is state-independent, so the batch mean changes nothing).
    """
    return (log_std + 0.5 + _HALF_LOG_2PI).mean()


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

    def act(
        self, obs: TensorObs, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Sample actions for a batch: (actions (B, A), log-probs (B,), values (B,))."""
        mean = self.action_mean(obs)
        noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
        actions = mean + torch.exp(self.log_std) * noise
        return actions, gaussian_log_prob(actions, mean, self.log_std), self.value(obs)

    def evaluate(
        self, obs: TensorObs, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Log-probs (B,), mean entropy per action dimension (scalar) and values (B,)."""
        mean = self.action_mean(obs)
        log_prob = gaussian_log_prob(actions, mean, self.log_std)
        return log_prob, gaussian_entropy(self.log_std), self.value(obs)
