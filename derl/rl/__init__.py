"""Lifetime learning: PPO with the paper's actor-critic on any batched environment.

`train(env, PPOConfig(...))` returns a `TrainResult` with the fitness, the learning curve, timing
and a `Checkpoint`; `Policy.from_checkpoint` turns one back into a deterministic numpy policy.
Environments conform to the `BatchedEnv` protocol; `GymBatchedEnv` wraps gymnasium ones.
"""

from derl.lazy import exports

# imported on first use: `derl.rl.config` alone needs no torch
__getattr__, __all__ = exports(
    __name__,
    {
        "checkpoint": ("Checkpoint", "Policy"),
        "config": ("PPOConfig", "PPOHyperparameters"),
        "env_api": ("BatchedEnv", "Obs", "StepResult"),
        "episodes": ("EpisodeLog",),
        "gym_adapter": ("GymBatchedEnv",),
        "network": ("ActorCritic",),
        "normalize": ("ObsNormalizer", "RewardScaler", "RunningMeanStd"),
        "ppo": ("Progress", "TimeSplit", "TrainResult", "compute_gae", "train"),
    },
)
