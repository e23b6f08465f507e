"""DERL's science, importable without the bus: bodies, worlds, learning, evolution, analysis.

``import derl`` registers every task as a gymnasium environment, ``derl/<Task>-v0`` (e.g.
``gymnasium.make("derl/VT-v0", genome="body.json", render_mode="rgb_array")``; the environments
themselves are imported on first `gymnasium.make`), and offers `load_trained` (a trained body
that acts: `derl.replay.Trained`) and `__version__` (the installed package's).
"""

from importlib.metadata import PackageNotFoundError, version
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


def register_gym_envs() -> None:
    """Register ``derl/<Task>-v0`` for every task in gymnasium's registry (idempotent)."""
    for gym_name, task in GYM_TASKS.items():
        env_id = f"derl/{gym_name}-v0"
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point=GYM_ENTRY_POINT, kwargs={"task": task})


register_gym_envs()

_getattr, _names = exports(__name__, {"replay": ("load_trained",)})
__all__ = ["GYM_TASKS", "__version__", "register_gym_envs", *_names]


def __getattr__(name: str) -> object:
    """`load_trained`, imported on first use (it imports the simulation and torch)."""
    return _getattr(name)
