"""The PPO loss as defined: the released code's clipped surrogate, clipped value loss and entropy
bonus on the actor-critic, in torch with autograd (CleanRL's form).

Training minimises this loss, but runs it and its gradient written out by hand (`derl.rl.fused`,
several times faster on these small layers); tests/test_ppo.py checks that its values and
gradient are this definition's. A step on a minibatch: none where `approx_kl` exceeds
``kl_stop`` (the released code's early stop), else the gradient of `PPOLoss.total`, its norm
clipped to ``max_grad_norm``, and one Adam step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from derl.rl.network import ActorCritic, TensorObs


@dataclass(frozen=True)
class PPOCoefficients:
    """The loss's constants and the step's limits (the config's values)."""

    clip: float
    value_clip: float
    value_coef: float
    entropy_coef: float
    max_grad_norm: float
    kl_stop: float


class Samples(NamedTuple):
    """A minibatch's (B, A) actions and their (B,) log-probabilities when sampled, advantages,
    values when sampled and returns."""

    actions: torch.Tensor
    old_log_prob: torch.Tensor
    advantages: torch.Tensor
    old_values: torch.Tensor
    returns: torch.Tensor


class PPOLoss(NamedTuple):
    """`total`, to minimise, and its parts (scalars; `approx_kl` and `clip_fraction` without
    gradient): what PPO libraries log."""

    total: torch.Tensor
    policy: torch.Tensor
    value: torch.Tensor
    entropy: torch.Tensor
    approx_kl: torch.Tensor
    clip_fraction: torch.Tensor


def ppo_loss(net: ActorCritic, obs: TensorObs, batch: Samples, coef: PPOCoefficients) -> PPOLoss:
    """The loss of `net` on the minibatch of observations ``obs`` and samples ``batch``."""
    pi = torch.distributions.Normal(net.action_mean(obs), net.log_std.exp())
    log_ratio = pi.log_prob(batch.actions).sum(-1) - batch.old_log_prob
    ratio = log_ratio.exp()
    # the clipped surrogate objective, negated
    adv = batch.advantages
    clipped_ratio = ratio.clamp(1.0 - coef.clip, 1.0 + coef.clip)
    policy = -torch.min(ratio * adv, clipped_ratio * adv).mean()
    # the squared error of the value, or of the value moved at most value_clip from the old one,
    # whichever is larger
    value, old, ret = net.value(obs), batch.old_values, batch.returns
    clipped = old + (value - old).clamp(-coef.value_clip, coef.value_clip)
    value_loss = 0.5 * torch.max((value - ret).square(), (clipped - ret).square()).mean()
    entropy = pi.entropy().mean()  # over the batch and the action dimensions (the released code)
    total = policy + coef.value_coef * value_loss - coef.entropy_coef * entropy
    with torch.no_grad():
        approx_kl = -log_ratio.mean()  # mean(old log-prob - log-prob): the early stop's
        clip_fraction = ((ratio - 1.0).abs() > coef.clip).float().mean()
    return PPOLoss(total, policy, value_loss, entropy, approx_kl, clip_fraction)
