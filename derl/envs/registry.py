"""Tasks by name: the three evolution worlds (`WORLDS`) and the eight test tasks (`TEST_TASKS`)."""

from __future__ import annotations

from typing import Any

from derl.envs.eval_tasks import (
    Escape,
    Exploration,
    Incline,
    ManipulateBall,
    Obstacle,
    Patrol,
    PointNav,
    PushBoxIncline,
)
from derl.envs.task import Task
from derl.envs.worlds import Flat, Manipulation, Variable

WORLDS = (Flat, Variable, Manipulation)
TEST_TASKS = (
    Patrol,
    PointNav,
    Obstacle,
    Exploration,
    Escape,
    Incline,
    PushBoxIncline,
    ManipulateBall,
)
TASKS: dict[str, type[Task]] = {task.name: task for task in (*WORLDS, *TEST_TASKS)}


def make_task(name: str, **options: Any) -> Task:
    """A task by name, with optional constructor options (e.g. ``terrain=TerrainConfig(...)``)."""
    try:
        task = TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; choose from {', '.join(TASKS)}") from None
    return task(**options)
