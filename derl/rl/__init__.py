"""Lifetime learning: PPO with the paper's actor-critic on any batched environment.

`train(env, PPOConfig(...))` returns a `TrainResult` with the fitness, the learning curve, timing
and a `Checkpoint`; `Policy.from_checkpoint` turns one back into a deterministic numpy policy.
Environments conform to the `BatchedEnv` protocol; `GymBatchedEnv` wraps gymnasium ones.
"""

from typing import TYPE_CHECKING

from derl.lazy import exports

if TYPE_CHECKING:  # imported on first use (below): `derl.rl.config` alone needs no torch
    from derl.rl.checkpoint import Checkpoint, Policy
    from derl.rl.config import PPOConfig
    from derl.rl.env_api import BatchedEnv, Obs, StepResult
    from derl.rl.episodes import EpisodeLog
    from derl.rl.gym_adapter import GymBatchedEnv
    from derl.rl.network import ActorCritic
    from derl.rl.normalize import ObsNormalizer, RewardScaler, RunningMeanStd
    from derl.rl.ppo import Progress, TimeSplit, TrainResult, compute_gae, train

_HOMES = {
    "ActorCritic": "network",
    "BatchedEnv": "env_api",
    "Checkpoint": "checkpoint",
    "EpisodeLog": "episodes",
    "GymBatchedEnv": "gym_adapter",
    "Obs": "env_api",
    "ObsNormalizer": "normalize",
    "PPOConfig": "config",
    "Policy": "checkpoint",
    "Progress": "ppo",
    "RewardScaler": "normalize",
    "RunningMeanStd": "normalize",
    "StepResult": "env_api",
    "TimeSplit": "ppo",
    "TrainResult": "ppo",
    "compute_gae": "ppo",
    "train": "ppo",
}
__all__ = [
    "ActorCritic",
    "BatchedEnv",
    "Checkpoint",
    "EpisodeLog",
    "GymBatchedEnv",
    "Obs",
    "ObsNormalizer",
    "PPOConfig",
    "Policy",
    "Progress",
    "RewardScaler",
    "RunningMeanStd",
    "StepResult",
    "TimeSplit",
    "TrainResult",
    "compute_gae",
    "train",
]
__getattr__ = exports(__name__, _HOMES)
