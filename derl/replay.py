"""A trained body acting again: loaded from a folder (genome, checkpoint, task), its episodes
played with the deterministic policy, the first one filmed if asked (`derl rollout`).

Two kinds of folder hold a trained body, in one layout (`derl.agent_folder`): the output of
`derl train` and a run's ``best/NN-agent`` folder. From Python::

    import derl

    agent = derl.load_trained("runs/body-ft")      # NotTrained says what the folder lacks
    env = agent.gym_env(render_mode="rgb_array")   # its body in its task, as a gymnasium env
    obs, _ = env.reset(seed=0)
    for _ in range(1000):
        obs, reward, terminated, truncated, info = env.step(agent.act(obs))
        if terminated or truncated:
            break
"""

from __future__ import annotations

import pickle
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from derl.agent_folder import AgentFolder, NotTrained
from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.envs.registry import TASK_REGISTRY
from derl.plugins import PluginError
from derl.unimal import Genome

if TYPE_CHECKING:
    import gymnasium

    from derl.rl import Policy

EPISODE_STEPS = EnvConfig().episode_steps


@dataclass(frozen=True)
class Trained:
    """A body, the task it learnt, and its deterministic policy."""

    genome: Genome
    task: str
    policy: Policy

    @classmethod
    def of(cls, genome: Genome, task: str, checkpoint: bytes) -> Trained:
        """`NotTrained` when the checkpoint cannot be read."""
        from derl.rl import Policy  # torch: only once a policy is wanted

        try:
            return cls(genome, task, Policy.from_checkpoint(checkpoint))
        except (ValueError, RuntimeError, pickle.UnpicklingError) as error:
            raise NotTrained(f"unreadable checkpoint: {error}") from None

    @classmethod
    def load(cls, folder: Path) -> Trained:
        """The trained body of `folder`; `NotTrained` says what is missing or unreadable."""
        agent = AgentFolder(folder)
        missing = agent.missing()
        if missing:
            raise NotTrained(
                f"{folder} holds no trained body: no {', no '.join(missing)} (a `derl train` "
                "output folder or a run's best/NN-agent folder has them)"
            )
        task = agent.task()
        try:
            TASK_REGISTRY.get(task)  # a plugin's task: installed here too?
        except PluginError as error:
            raise NotTrained(f"{folder}: {error}") from None
        try:
            checkpoint = agent.checkpoint()
        except OSError as error:
            raise NotTrained(f"{folder}: cannot read its checkpoint: {error}") from None
        return cls.of(agent.genome(), task, checkpoint)

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The policy's mean action, clipped to [-1, 1]: for one observation (a dict of
        (dim,) arrays, as `gym_env`'s) an (A,) array, for a batch of them ((N, dim) arrays, as
        a `derl.envs.UnimalEnv`'s) (N, A)."""
        one = next(iter(obs.values())).ndim == 1
        actions = self.policy({key: value[None] if one else value for key, value in obs.items()})
        return actions[0] if one else actions

    def gym_env(self, render_mode: str | None = None, **options: Any) -> gymnasium.Env:
        """The body in the task it learnt, as ``gymnasium.make`` makes it (its registered id,
        `gym_id`: the same wrappers), with `UnimalGymEnv`'s `render_mode`, frame size and task
        options."""
        import gymnasium

        from derl.envs.gym_env import gym_id

        return gymnasium.make(gym_id(self.task), genome=self.genome, render_mode=render_mode,
                              **options)  # fmt: skip


def load_trained(folder: str | Path) -> Trained:
    """The trained body of `folder` (`Trained.load`): `derl train`'s output or a run's
    best/NN-agent folder."""
    return Trained.load(Path(folder))


@dataclass(frozen=True)
class Episode:
    """One episode: the sum of the task's fitness component, its length, how it ended, and its
    frames (RGB, one per control step) if it was filmed."""

    component: str
    total: float
    steps: int
    fell: bool
    frames: list[np.ndarray] = field(default_factory=list)


def play(
    trained: Trained,
    episodes: int,
    seed: int = 0,
    episode_steps: int = EPISODE_STEPS,
    film: tuple[int, int] | None = None,
    film_every: int = 1,
) -> Iterator[Episode]:
    """`episodes` episodes of one copy, each at most `episode_steps` control steps; the first is
    filmed at `film` = (width, height) pixels when given (offscreen OpenGL, `MUJOCO_GL`), a
    frame every `film_every` control steps (the others are not rendered)."""
    from derl.envs.video import FrameRecorder

    task = make_task(trained.task)
    env = UnimalEnv(trained.genome, task, EnvConfig(num_envs=1, episode_steps=episode_steps), seed)
    component = task.fitness_component
    recorder = None if film is None else FrameRecorder(env, *film)
    try:
        obs = env.reset(seed)
        for episode in range(episodes):
            total, steps, frames = 0.0, 0, []
            while True:
                if recorder is not None and episode == 0:
                    if steps % film_every == 0:
                        frames.append(recorder.frame())
                    else:
                        recorder.follow()
                step = env.step(trained.act(obs))
                obs, steps = step.obs, steps + 1
                total += float(step.components[component][0])
                if step.terminated[0] or step.truncated[0]:
                    break
            yield Episode(component, total, steps, bool(step.terminated[0]), frames)
    finally:
        if recorder is not None:
            recorder.close()
