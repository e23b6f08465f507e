"""Tasks by name: the three evolution worlds and the eight test tasks."""

from __future__ import annotations

from typing import Any

from derl.envs.task import Task
from derl.envs.worlds import Flat, Manipulation, Variable

TASKS: dict[str, type[Task]] = {task.name: task for task in (Flat, Variable, Manipulation)}


def make_task(name: str, **options: Any) -> Task:
    """A task by name, with optional constructor options (e.g. ``terrain=TerrainConfig(...)``)."""
    try:
        task = TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; choose from {', '.join(TASKS)}") from None
    return task(**options)
