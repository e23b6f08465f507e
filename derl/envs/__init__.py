"""Environments: terrain, the evolution worlds and test tasks, batched simulation of UNIMALs."""

from derl.envs.batched import EnvConfig, StepResult, UnimalEnv
from derl.envs.gym_env import UnimalGymEnv
from derl.envs.registry import TASKS, make_task
from derl.unimal import Genome


def make_env(
    genome: Genome, task: str, num_envs: int = 32, seed: int = 0, **task_options: object
) -> UnimalEnv:
    """`num_envs` copies of a body in a task, ready to `reset` and `step`."""
    return UnimalEnv(genome, make_task(task, **task_options), EnvConfig(num_envs=num_envs), seed)


__all__ = [
    "TASKS",
    "EnvConfig",
    "StepResult",
    "UnimalEnv",
    "UnimalGymEnv",
    "make_env",
    "make_task",
]
