"""DERL's science, importable without the bus: bodies, worlds, learning, evolution, analysis.

``import derl`` registers every task, a plugin's too, as a gymnasium environment,
``derl/<Task>-v0`` (e.g.
``gymnasium.make("derl/VT-v0", genome="body.json", render_mode="rgb_array")``; the environments
themselves are imported on first `gymnasium.make`), and offers `load_trained` (a trained body
that acts: `derl.replay.Trained`) and `__version__` (the installed package's).
"""

from importlib.metadata import PackageNotFoundError, entry_points, version
from typing import TYPE_CHECKING

import gymnasium

from derl.lazy import exports

if TYPE_CHECKING:  # the name for type checkers, which do not run `__getattr__`
    from derl.replay import load_trained as load_trained

try:
    __version__ = version("derl")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

GYM_TASKS = {
    "FT": "ft",
    "VT": "vt",
    "MVT": "mvt",
    "Patrol": "patrol",
    "PointNav": "point_nav",
    "Obstacle": "obstacle",
    "Exploration": "exploration",
    "Escape": "escape",
    "Incline": "incline",
    "PushBoxIncline": "push_box_incline",
    "ManipulateBall": "manipulate_ball",
}
"""Every task's gymnasium name (`derl.envs.task.Task.gym_name`, which the tests check this
against) and derl name, so that registering them needs no simulation code."""
GYM_ENTRY_POINT = "derl.envs.gym_env:UnimalGymEnv"
GYM_VECTOR_ENTRY_POINT = "derl.envs.gym_env:UnimalVectorEnv"
GYM_EPISODE_STEPS = 1000
"""An episode's control steps (`derl.envs.batched.EnvConfig.episode_steps`, which the tests check
this against): the specs' `max_episode_steps`."""


def gym_name(task: str) -> str:
    """A plugin task's gymnasium name: its entry point's name in CamelCase (``my_stairs``:
    ``MyStairs``, registered as ``derl/MyStairs-v0``)."""
    return "".join(part[:1].upper() + part[1:] for part in task.replace("-", "_").split("_"))


def register_gym_envs() -> None:
    """Register ``derl/<Task>-v0`` for every task in gymnasium's registry (idempotent): the
    built-ins, and the tasks of installed plugins (entry point group ``derl.tasks``, by name only:
    nothing of theirs is imported before `gymnasium.make`)."""
    plugins = {
        gym_name(point.name): point.name
        for point in entry_points(group="derl.tasks")
        if point.name not in GYM_TASKS.values()
    }
    for name, task in {**plugins, **GYM_TASKS}.items():
        env_id = f"derl/{name}-v0"
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point=GYM_ENTRY_POINT, kwargs={"task": task},
                               vector_entry_point=GYM_VECTOR_ENTRY_POINT,
                               max_episode_steps=GYM_EPISODE_STEPS)  # fmt: skip


register_gym_envs()

_getattr, _names = exports(__name__, {"replay": ("load_trained",)})
__all__ = ["GYM_TASKS", "__version__", "gym_name", "register_gym_envs", *_names]


def __getattr__(name: str) -> object:
    """`load_trained`, imported on first use (it imports the simulation and torch)."""
    return _getattr(name)
