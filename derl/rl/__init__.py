"""Lifetime learning: PPO with the paper's actor-critic on any batched environment.

`train(env, PPOConfig(...))` returns a `TrainResult` with the fitness, the learning curve, timing
and a `Checkpoint`; `Policy.from_checkpoint` turns one back into a deterministic numpy policy.
Environments conform to the `BatchedEnv` protocol; `GymBatchedEnv` wraps gymnasium ones.
"""

from typing import TYPE_CHECKING

from derl.lazy import exports

if TYPE_CHECKING:  # the names for type checkers, which do not run `__getattr__`
    from derl.rl.checkpoint import Checkpoint as Checkpoint
    from derl.rl.checkpoint import Policy as Policy
    from derl.rl.config import PPOConfig as PPOConfig
    from derl.rl.config import PPOHyperparameters as PPOHyperparameters
    from derl.rl.env_api import BatchedEnv as BatchedEnv
    from derl.rl.env_api import Obs as Obs
    from derl.rl.env_api import StepResult as StepResult
    from derl.rl.episodes import EpisodeLog as EpisodeLog
    from derl.rl.gym_adapter import GymBatchedEnv as GymBatchedEnv
    from derl.rl.network import ActorCritic as ActorCritic
    from derl.rl.normalize import ObsNormalizer as ObsNormalizer
    from derl.rl.normalize import RewardScaler as RewardScaler
    from derl.rl.normalize import RunningMeanStd as RunningMeanStd
    from derl.rl.ppo import Progress as Progress
    from derl.rl.ppo import TimeSplit as TimeSplit
    from derl.rl.ppo import TrainResult as TrainResult
    from derl.rl.ppo import compute_gae as compute_gae
    from derl.rl.ppo import train as train

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
