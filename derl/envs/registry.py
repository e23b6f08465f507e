"""Tasks by name: the three evolution worlds (`WORLDS`) and the eight test tasks (`TEST_TASKS`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from derl.envs import eval_tasks, worlds
from derl.envs.task import Task

TASKS: dict[str, Callable[..., Task]] = {
    "ft": worlds.ft,
    "vt": worlds.vt,
    "mvt": worlds.mvt,
    "patrol": eval_tasks.patrol,
    "point_nav": eval_tasks.point_nav,
    "obstacle": eval_tasks.obstacle,
    "exploration": eval_tasks.exploration,
    "escape": eval_tasks.escape,
    "incline": eval_tasks.incline,
    "push_box_incline": eval_tasks.push_box_incline,
    "manipulate_ball": eval_tasks.manipulate_ball,
}
"""Every task's factory: its keyword options (e.g. ``terrain=TerrainConfig(...)``) to a `Task`."""

WORLDS = ("ft", "vt", "mvt")
"""The evolution worlds (appendix A)."""

TEST_TASKS = (
    "patrol",
    "point_nav",
    "obstacle",
    "exploration",
    "escape",
    "incline",
    "push_box_incline",
    "manipulate_ball",
)
"""The paper's eight test tasks (appendix C)."""


def make_task(name: str, **options: Any) -> Task:
    """A task by name, with optional factory options (e.g. ``terrain=TerrainConfig(...)``)."""
    try:
        factory = TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; choose from {', '.join(TASKS)}") from None
    return factory(**options)
