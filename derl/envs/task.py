"""What a task is: a composition of parts (an arena, props, reward terms, observations, a
success test) that the environment drives through a few calls per step.

A part overrides the hooks of `Part` it needs; `Task` calls each hook only on the parts that
override it, in the order the task lists them (arena, props, rewards, observations, success),
so a step costs a handful of calls. Parts see the environment through `EnvView` and answer with
numpy arrays over all copies at once. The environment (`derl.envs.batched`) owns the stepping,
the body's own observations, the fall test, time limits and resets.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import reduce
from typing import ClassVar

import mujoco
import numpy as np

from derl.envs.terrain_stack import TerrainStack
from derl.envs.view import EnvView

Arrays = dict[str, np.ndarray]
HOOKS = ("build", "bind", "start", "reset", "posed", "placed", "update")


class Part:
    """A piece of a task. Every hook is optional; `Task` calls only those a part overrides."""

    def build(self, spec: mujoco.MjSpec) -> None:
        """Add bodies, geoms or assets to the body's model (before it is compiled)."""

    def bind(self, env: EnvView) -> None:
        """The copies exist: look up joints, size per-copy state."""

    def start(self) -> None:
        """A new seeded run begins: forget anything carried between episodes."""

    def reset(self, env: EnvView, ids: np.ndarray) -> None:
        """New episodes for copies ``ids``, before their bodies are placed: terrain, objects."""

    def posed(self, env: EnvView, ids: np.ndarray) -> None:
        """The bodies of ``ids`` are in their start poses (their state only: MuJoCo has not yet
        computed positions or contacts from it)."""

    def placed(self, env: EnvView, ids: np.ndarray) -> None:
        """The bodies of ``ids`` are placed: record start-of-episode quantities."""

    def update(self, env: EnvView) -> None:
        """After each control step, before the rewards: advance per-step state."""


class Arena(Part):
    """The ground. ``half``: half extents (x, y); a copy whose head leaves them (less a margin)
    ends. Objects rest on it rotated by ``tilt`` (a quaternion), their centre raised by their
    half height / ``cos_slope``. ``terrains``: the copies' heightfields, where the arena has
    them (set once the copies exist; None for a plane)."""

    half: tuple[float, float]
    tilt: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    cos_slope: float = 1.0
    terrains: TerrainStack | None = None

    @property
    def diagonal(self) -> float:
        """m: the longest straight line inside the arena, the furthest anything in it can get
        from where it was."""
        return 2 * math.hypot(*self.half)

    def ground(self, xy: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        """(len(xy),) ground height under point ``xy[k]`` of copy ``ids[k]`` (default: copy k)."""
        raise NotImplementedError

    def fall_ground(self, xy: np.ndarray) -> np.ndarray:
        """(len(xy),) the ground under point ``xy[k]`` of copy k as the fall test reads it: the
        released code's (`UnimalHeightObs`), at the corner of the grid cell the point is in (its
        position floored to whole cells, `Terrain.pos_to_idx`)."""
        raise NotImplementedError

    def top(self, xy: np.ndarray, half: float, ids: np.ndarray | None = None) -> np.ndarray:
        """(len(xy),) the highest ground under the square of half side ``half`` around point
        ``xy[k]`` of copy ``ids[k]``, where an object of that footprint rests (on a plane: the
        ground under its centre, the object tilted with the plane)."""
        return self.ground(xy, ids)


@dataclass(frozen=True)
class EpisodeLimits:
    """What bounds an episode: its control step (s), its length in control steps, and the arena's
    `Arena.diagonal` (m)."""

    control_dt: float
    steps: int
    diagonal: float


class RewardTerm(Part):
    """One weighted term of the reward (the reward is their sum), reported under `name`: a pure
    function of the environment and of the props' state (advanced in their `update`), keeping
    none of its own, so that the terms' order does not matter.

    A term states how large it can be (`step_bound`, or a tighter `episode_bound`): a fitness is
    a mean of episode sums of terms, so what a report may claim is derived from them (`Task.
    fitness_bound`). A term that states neither is unbounded, and so is a fitness that sums it."""

    name: ClassVar[str]

    def __call__(self, env: EnvView) -> np.ndarray:
        """(N,) the term for the last step."""
        raise NotImplementedError

    def step_bound(self, limits: EpisodeLimits) -> float:
        """The largest |term| in one control step (inf: unbounded)."""
        return math.inf

    def episode_bound(self, limits: EpisodeLimits) -> float:
        """The largest |sum of the term over one episode|: `limits.steps` x `step_bound`, unless
        the term states a tighter one (a distance gained sums to at most the arena's diagonal)."""
        return limits.steps * self.step_bound(limits)


class Observation(Part):
    """One observation type the task adds: `size` float32 values per copy."""

    name: ClassVar[str]
    size: int

    def __call__(self, env: EnvView, ids: np.ndarray) -> np.ndarray:
        """(len(ids), size) the observation of copies ``ids``."""
        raise NotImplementedError


class Success(Part):
    """A test ending episodes because the task is achieved."""

    def __call__(self, env: EnvView) -> np.ndarray:
        """(N,) bool: copies that achieved the task in the last step."""
        raise NotImplementedError


@dataclass(eq=False)
class Task:
    """One world or test task: its parts, its spawn point, and the reward component that is
    the fitness. ``metrics`` are components reported beside the terms: each the sum of the
    named terms (e.g. ``{"manipulation": ("reach", "push")}``). ``fall_ratio``, where set,
    replaces the environment's (`EnvConfig.fall_ratio`): the head falls below this fraction of
    its resting height."""

    name: str
    gym_name: str
    fitness_component: str
    arena: Arena
    spawn: tuple[float, float]
    rewards: tuple[RewardTerm, ...]
    observations: tuple[Observation, ...] = ()
    props: tuple[Part, ...] = ()
    success: Success | None = None
    metrics: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    fall_ratio: float | None = None
    _hooks: dict[str, tuple[Callable[..., None], ...]] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        terms = [term.name for term in self.rewards]
        if len(set(terms)) < len(terms):
            raise ValueError(f"{self.name}: reward terms share a name: {terms}")
        for metric, summed in self.metrics.items():
            if not summed or not set(summed) <= set(terms):
                raise ValueError(f"{self.name}: metric {metric} sums unknown terms {summed}")
        if self.fitness_component not in {*terms, *self.metrics}:
            raise ValueError(f"{self.name}: no component {self.fitness_component!r}")
        parts = (self.arena, *self.props, *self.rewards, *self.observations)
        parts += (self.success,) if self.success is not None else ()
        self._hooks = {
            hook: tuple(
                getattr(part, hook)
                for part in parts
                if getattr(type(part), hook) is not getattr(Part, hook)
            )
            for hook in HOOKS
        }

    def fitness_bound(self, control_dt: float, episode_steps: int) -> float:
        """The largest |fitness| of this task: the sum of the episode bounds of the terms its
        fitness component sums (a mean of episode sums cannot exceed it; inf where a term is
        unbounded)."""
        limits = EpisodeLimits(control_dt, episode_steps, self.arena.diagonal)
        summed = self.metrics.get(self.fitness_component, (self.fitness_component,))
        return sum(term.episode_bound(limits) for term in self.rewards if term.name in summed)

    def obs_spaces(self) -> dict[str, int]:
        """Observation types the task adds, with their sizes."""
        return {obs.name: obs.size for obs in self.observations}

    def build(self, spec: mujoco.MjSpec) -> None:
        for build in self._hooks["build"]:
            build(spec)

    def bind(self, env: EnvView) -> None:
        for bind in self._hooks["bind"]:
            bind(env)

    def start(self) -> None:
        for start in self._hooks["start"]:
            start()

    def reset(self, env: EnvView, ids: np.ndarray) -> None:
        for reset in self._hooks["reset"]:
            reset(env, ids)

    def posed(self, env: EnvView, ids: np.ndarray) -> None:
        for posed in self._hooks["posed"]:
            posed(env, ids)

    def placed(self, env: EnvView, ids: np.ndarray) -> None:
        for placed in self._hooks["placed"]:
            placed(env, ids)

    def step(self, env: EnvView) -> Arrays:
        """Advance the parts' per-step state; the reward terms of the last step."""
        for update in self._hooks["update"]:
            update(env)
        return {term.name: term(env) for term in self.rewards}

    def metric_values(self, terms: Arrays) -> Arrays:
        """The metrics of the last step, from its reward terms."""
        return {
            name: reduce(operator.add, (terms[term] for term in summed))
            for name, summed in self.metrics.items()
        }

    def observe(self, env: EnvView, ids: np.ndarray) -> Arrays:
        """The task's observations of copies ``ids``."""
        return {obs.name: obs(env, ids) for obs in self.observations}
