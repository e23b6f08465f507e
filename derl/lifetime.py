"""Lifetime learning of one body in one task: build its batched environment, train a controller
from scratch with PPO, and measure what evolution and the analyses need.

Fitness is the released code's: the mean, over the last PPO iterations, of each iteration's mean
episode sum of the task's selection component (forward progress for FT/VT, reach + push for MVT)
over the last 10 finished episodes. The window is the released code's share of its training, its
last `FITNESS_ITERATIONS` of `RELEASED_ITERATIONS`, of this training's iterations: the code's
window at the paper's 5M steps (about the last 410k), the same last 8 % of a shorter one. Cost of
work over the episodes finished in the same window is E / (M g r): E the episode's sum of |joint
torque|, M the body's mass, r its selection reward (undefined, NaN, when r <= 0).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel, ConfigDict

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.rl.config import PPOConfig
from derl.unimal import Genome

if TYPE_CHECKING:
    from derl.rl.inherit import Inheritance
    from derl.rl.ppo import Progress, TrainResult

Saved = Callable[["LifetimeResult", "TrainResult", bytes], None]
"""Called with the summary and the result so far and the training's state (`learn`'s `save`)."""

GRAVITY = 9.81
FITNESS_ITERATIONS = 100
"""The released code's fitness: the mean of its last 100 per-iteration values."""
RELEASED_ITERATIONS = 5_000_000 // (32 * 128)
"""The iterations of the released code's trainings (`calculate_max_iters`: 1220)."""


class LifetimeResult(BaseModel):
    """What one lifetime of learning produced, small enough to travel in a message."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    task: str
    fitness: float
    fitness_source: str
    fitness_episodes: int
    curve_steps: list[int]
    curve_returns: list[float]
    energy: float  # mean sum of |joint torque| per final episode
    mass: float
    cost_of_work: float
    episodes: int
    env_steps: int
    wall_time_s: float
    steps_per_second: float
    unstable_steps: int
    constraint_rows: int  # MuJoCo's constraint rows summed over the control steps (`UnimalEnv`)
    time_split: dict[str, float]


def fitness_window(total_steps: int, batch_size: int) -> int:
    """The env steps of the fitness window of a training of `total_steps` in iterations of
    `batch_size`: the released code's share, `FITNESS_ITERATIONS` of `RELEASED_ITERATIONS`, of
    its iterations, rounded to whole ones (at least one)."""
    iterations = total_steps // batch_size
    share = round(FITNESS_ITERATIONS * iterations / RELEASED_ITERATIONS)
    return max(1, share) * batch_size


def ppo_config(task: str, steps: int, seed: int, **overrides: object) -> PPOConfig:
    """The paper's PPO for a task: its fitness component and the released code's fitness window,
    scaled to the budget."""
    base = PPOConfig(total_steps=steps, seed=seed, **overrides)
    component = make_task(task).fitness_component
    window = fitness_window(base.total_steps, base.batch_size)
    return base.model_copy(update={"fitness_component": component, "fitness_window_steps": window})


def with_budget(config: PPOConfig, steps: int) -> PPOConfig:
    """`config` with a budget of `steps` and the fitness window scaled to it (`ValidationError`
    below one rollout)."""
    window = fitness_window(steps, config.batch_size)
    changed = {"total_steps": steps, "fitness_window_steps": window}
    return PPOConfig.model_validate({**config.model_dump(), **changed})


def learn(
    genome: Genome,
    task: str,
    config: PPOConfig,
    callback: Callable[[Progress], None] | None = None,
    nthread: int = 1,
    *,
    save: Saved | None = None,
    every: int = 0,
    stop: threading.Event | None = None,
    resume: bytes | None = None,
    last: bool = False,
    parent: tuple[Genome, bytes] | None = None,
) -> tuple[LifetimeResult, TrainResult]:
    """Train a fresh controller for `genome` in `task`; returns the summary and the full result.
    With `save`, the training's state is saved every `every` iterations (0: never), once `stop`
    is set, after which it returns what it did, and with `last` at the end
    (`derl.rl.ppo.Saver`); `resume` (such a state) goes on from it, bit for bit, or extends it
    where `config` has a larger budget. `parent` (its body and its checkpoint's bytes): the
    controller starts from the parent's where their parts match (`derl.rl.inherit`)."""
    from derl.rl.ppo import Saver, train  # torch: imported by trainings only, not by config users

    env = UnimalEnv(
        genome,
        make_task(task),
        EnvConfig(num_envs=config.num_envs, nthread=nthread),
        seed=config.seed,
    )
    initial = None if parent is None else inheritance(parent[0], parent[1], task, env)
    saver = None
    if save is not None:

        def saved(result: TrainResult, state: bytes) -> None:
            save(summarize(env, task, config, result), result, state)

        saver = Saver(saved, every, stop or threading.Event(), last)
    result = train(env, config, callback, saver=saver, resume=resume, initial=initial)
    return summarize(env, task, config, result), result


def inheritance(parent: Genome, checkpoint: bytes, task: str, child: UnimalEnv) -> Inheritance:
    """How `child`'s controller (in `task`) starts from `parent`'s, its trained `checkpoint`
    in the same task: the two bodies' parts matched by name (`derl.rl.inherit`)."""
    from derl.rl.checkpoint import Checkpoint
    from derl.rl.inherit import Inheritance, Layout

    ancestor = UnimalEnv(parent, make_task(task), EnvConfig(num_envs=1))
    return Inheritance(
        Checkpoint.from_bytes(checkpoint),
        Layout(tuple(ancestor.proprioception_labels), tuple(ancestor.action_labels)),
        Layout(tuple(child.proprioception_labels), tuple(child.action_labels)),
    )


def summarize(env: UnimalEnv, task: str, config: PPOConfig, result: TrainResult) -> LifetimeResult:
    """What evolution and the analyses keep of a training (so far) of `env`'s body."""
    mass = float(env.model.body_subtreemass[env.head])
    log = result.episodes
    final = log.finish_step > result.env_steps - config.fitness_window_steps
    if not final.any():
        final = np.arange(len(log)) >= len(log) - config.recent_episodes
    energy = float(log.components["energy"][final].mean()) if final.any() else float("nan")
    reward = result.fitness
    cost = energy / (mass * GRAVITY * reward) if reward > 0 else float("nan")
    steps, returns = zip(*result.curve, strict=True) if result.curve else ((), ())
    return LifetimeResult(
        task=task,
        fitness=result.fitness,
        fitness_source=result.fitness_source,
        fitness_episodes=result.fitness_episodes,
        curve_steps=list(steps),
        curve_returns=list(returns),
        energy=energy,
        mass=mass,
        cost_of_work=cost,
        episodes=len(log),
        env_steps=result.env_steps,
        wall_time_s=result.wall_time_s,
        steps_per_second=result.steps_per_second,
        unstable_steps=env.unstable_count,
        constraint_rows=env.constraint_rows,
        time_split={k: round(v, 3) for k, v in vars(result.time_split).items() if v is not None},
    )
