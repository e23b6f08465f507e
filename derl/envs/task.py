"""What a task is: the arena it adds to a body's model, its observations, rewards and endings.

A task sees the batch through `Sim` (live arrays over all copies) and answers with numpy arrays
over all copies at once. The environment (`derl.envs.batched`) owns the stepping, the body's own
observations, the fall test, time limits and resets; a task adds everything world-specific.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, ClassVar

import mujoco
import numpy as np

if TYPE_CHECKING:
    from derl.envs.batched import UnimalEnv as Sim

Arrays = dict[str, np.ndarray]


class Task(ABC):
    """One world and its reward. Subclasses set `name` and `fitness_component`."""

    name: ClassVar[str]
    gym_name: ClassVar[str]
    fitness_component: ClassVar[str]
    # Half extents (x, y) of the arena; a copy whose head leaves it (less a 1 m margin) ends.
    arena: tuple[float, float]
    spawn: tuple[float, float]

    @abstractmethod
    def build(self, spec: mujoco.MjSpec) -> None:
        """Add the arena, objects and markers to the body's model."""

    def setup(self, sim: Sim) -> None:
        """Bind what the task needs once the batch exists."""

    def obs_spaces(self) -> dict[str, int]:
        """Observation types the task adds, with their sizes."""
        return {}

    def start(self, sim: Sim) -> None:
        """A new seeded run begins: forget anything carried between episodes."""

    def reset(self, sim: Sim, ids: np.ndarray) -> None:
        """New episode for copies ``ids``: terrain, objects and goals (the body is placed after)."""

    def ground(self, sim: Sim, xy: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        """Ground height under point ``xy[k]`` of copy ``ids[k]`` (default: copy k)."""
        return np.zeros(len(xy))

    def placed(self, sim: Sim, ids: np.ndarray) -> None:
        """Called after the bodies of ``ids`` are placed: record start-of-episode quantities."""

    @abstractmethod
    def rewards(self, sim: Sim) -> Arrays:
        """Weighted reward terms of the last step; the reward is their sum."""

    def metrics(self, sim: Sim, terms: Arrays) -> Arrays:
        """Per-step quantities reported beside the reward terms (e.g. the fitness component)."""
        return {}

    def observe(self, sim: Sim, ids: np.ndarray) -> Arrays:
        """The task's observations of copies ``ids``, (len(ids), size) each."""
        return {}

    def success(self, sim: Sim) -> np.ndarray:
        """(N,) bool: copies whose episode ends because the task is achieved."""
        return np.zeros(sim.num_envs, dtype=bool)
