"""A trained policy as bytes, and the deterministic numpy policy rebuilt from it.

The bytes are `torch.save` of a plain dict of tensors, ints and strings, read back by a reader
that runs no pickled code and needs no torch (`derl.rl.checkpoint_format`, which has the layout).
Only the observation statistics are kept: the reward scale matters for training, not for acting.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from derl.rl.checkpoint_format import FORMAT, read_checkpoint
from derl.rl.config import PPOConfig
from derl.rl.network import ActorCritic
from derl.rl.normalize import ObsNormalizer


@dataclass(frozen=True)
class Checkpoint:
    """Actor-critic weights, observation statistics, the spaces they fit, and the config."""

    obs_spaces: dict[str, int]
    action_dim: int
    weights: dict[str, torch.Tensor]
    obs_stats: dict[str, np.ndarray]
    config: PPOConfig

    @classmethod
    def capture(cls, net: ActorCritic, obs_norm: ObsNormalizer, config: PPOConfig) -> Checkpoint:
        """Snapshot (copies) of a network and its observation normaliser."""
        return cls(
            obs_spaces=dict(net.obs_spaces),
            action_dim=net.action_dim,
            weights={k: v.detach().clone() for k, v in net.state_dict().items()},
            obs_stats=obs_norm.state_dict(),
            config=config,
        )

    def to_bytes(self) -> bytes:
        buffer = io.BytesIO()
        torch.save(
            {
                "format": FORMAT,
                "obs_spaces": self.obs_spaces,
                "action_dim": self.action_dim,
                "weights": self.weights,
                "obs_stats": {
                    k: torch.from_numpy(np.asarray(v)) for k, v in self.obs_stats.items()
                },
                "config": self.config.model_dump_json(),
            },
            buffer,
        )
        return buffer.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> Checkpoint:
        fields = read_checkpoint(data)
        return cls(
            obs_spaces=fields["obs_spaces"],
            action_dim=fields["action_dim"],
            weights={k: torch.from_numpy(v) for k, v in fields["weights"].items()},
            obs_stats=fields["obs_stats"],
            config=fields["config"],
        )


class Policy:
    """Deterministic (mean action) policy: dict of (N, dim) arrays in, (N, A) float32 out."""

    def __init__(self, net: ActorCritic, obs_norm: ObsNormalizer) -> None:
        self.net = net.eval()
        self.obs_norm = obs_norm

    @classmethod
    def from_checkpoint(cls, checkpoint: Checkpoint | bytes) -> Policy:
        if isinstance(checkpoint, bytes):
            checkpoint = Checkpoint.from_bytes(checkpoint)
        net = ActorCritic(checkpoint.obs_spaces, checkpoint.action_dim, initialize=False)
        net.load_state_dict(checkpoint.weights)
        config = checkpoint.config
        obs_norm = ObsNormalizer(checkpoint.obs_spaces, config.obs_clip)
        obs_norm.load_state_dict(checkpoint.obs_stats)
        return cls(net, obs_norm)

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Mean actions clipped to [-1, 1]; the normaliser's statistics stay frozen."""
        normalized = self.obs_norm.normalize(obs)
        with torch.inference_mode():
            mean = self.net.action_mean({k: torch.from_numpy(v) for k, v in normalized.items()})
        return np.clip(mean.numpy(), -1.0, 1.0)


STATE_FORMAT = 1
"""Version of a training state's layout (`state_to_bytes`)."""


def state_to_bytes(state: dict[str, Any]) -> bytes:
    """A training's state (`derl.rl.ppo`: tensors, numbers, strings, lists and dicts) as the
    bytes of `torch.save`, readable with ``weights_only=True``."""
    buffer = io.BytesIO()
    torch.save({"format": STATE_FORMAT, **state}, buffer)
    return buffer.getvalue()


def state_from_bytes(data: bytes) -> dict[str, Any]:
    """`state_to_bytes` undone; `ValueError` for another format."""
    state = torch.load(io.BytesIO(data), weights_only=True)
    if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
        found = state.get("format") if isinstance(state, dict) else None
        raise ValueError(f"training state format {found}, this derl reads {STATE_FORMAT}")
    return state
