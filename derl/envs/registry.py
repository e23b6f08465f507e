"""Tasks by name: the three evolution worlds (`WORLDS`), the eight test tasks (`TEST_TASKS`), and
the tasks of plugins (`TASK_REGISTRY`, entry point group ``derl.tasks``, or
``package.module:name``): a task is a factory returning a `Task` made of derl's parts and the
plugin's own."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from derl.envs import eval_tasks, worlds
from derl.envs.task import Task
from derl.plugins import PluginError, Registry

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


def _factory(loaded: object) -> Callable[..., Task]:
    if not callable(loaded):
        raise TypeError(f"{loaded!r} is not callable")
    return loaded


TASK_REGISTRY: Registry[Callable[..., Task]] = Registry("task", "derl.tasks", TASKS, _factory)
"""Every task's factory by name: the built-ins (`TASKS`) and the plugins."""


def make_task(name: str, **options: Any) -> Task:
    """A task by name (a built-in's, an installed plugin's, or ``package.module:name``), with
    optional factory options (e.g. ``terrain=TerrainConfig(...)``); `PluginError` (a
    `ValueError`) saying why there is none."""
    factory = TASK_REGISTRY.get(name)
    if name in TASKS:
        return factory(**options)
    try:
        task = factory(**options)
    except Exception as error:  # a plugin's factory may raise anything
        raise PluginError(
            f"task {name!r}: its factory raised {type(error).__name__}: {error}"
        ) from None
    if not isinstance(task, Task):
        raise PluginError(f"task {name!r}: its factory returned {task!r:.80}, not a Task")
    return task
