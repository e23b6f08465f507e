"""A checkpoint's layout, and its bytes read into fields without torch (`derl.rl.torch_archive`):
what `Checkpoint.from_bytes` turns into tensors, and what a coordinator checks a reported policy
with (`derl.policy_check`) without importing torch.

The bytes are `torch.save` of a plain dict: "format" (`FORMAT`), "obs_spaces" (type -> size),
"action_dim", "weights" (the network's state dict), "obs_stats" (the observation normaliser's
state) and "config" (the training's `PPOConfig` as JSON). Checkpoints of an earlier format
(`OLD_FORMATS` says how each differs) are refused with a `ValueError`.
"""

from __future__ import annotations

from typing import TypedDict

import numpy as np

from derl.rl import torch_archive
from derl.rl.config import PPOConfig

FORMAT = 3
"""Version of the byte layout and of what the policy sees: 3, a network of one observation type
has no fuse layer and proprioception has the limb ends in x and y (see `OLD_FORMATS`)."""
OLD_FORMATS = {
    1: "normalised every observation type (now only proprioception), so its policy would see "
    "other inputs than it was trained on",
    2: "gave a network of one observation type a third layer and observed the limb ends in 3-D, "
    "which its policy no longer has",
}


class CheckpointFields(TypedDict):
    """A checkpoint's contents, its tensors as numpy arrays."""

    obs_spaces: dict[str, int]
    action_dim: int
    weights: dict[str, np.ndarray]
    obs_stats: dict[str, np.ndarray]
    config: PPOConfig


def read_checkpoint(data: bytes) -> CheckpointFields:
    """The fields of checkpoint bytes of this `FORMAT`; `ValueError` for another format, and
    whatever a damaged or foreign file raises (`torch_archive.load`, a missing key)."""
    raw = torch_archive.load(data)
    if not isinstance(raw, dict):
        raise ValueError(f"a checkpoint holds a dict, this file a {type(raw).__name__}")
    version = raw.get("format", 1)
    if version != FORMAT:
        why = OLD_FORMATS.get(version, "is unknown")
        raise ValueError(
            f"checkpoint format {version}, this derl reads format {FORMAT}: format "
            f"{version} {why}; train it again"
        )
    weights, stats = dict(raw["weights"]), dict(raw["obs_stats"])
    if not all(isinstance(array, np.ndarray) for array in (*weights.values(), *stats.values())):
        raise ValueError("a checkpoint's weights and statistics are tensors")
    return CheckpointFields(
        obs_spaces=dict(raw["obs_spaces"]),
        action_dim=int(raw["action_dim"]),
        weights=weights,
        obs_stats=stats,
        config=PPOConfig.model_validate_json(raw["config"]),
    )
