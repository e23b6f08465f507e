"""What a task's parts may see of the environment: `EnvView`, a protocol `UnimalEnv` satisfies.

Parts read the batch through these named accessors only, never through the simulation batch
or private attributes. Arrays are live views over all N copies (rows), valid until the
environment is gone; parts copy what they keep. The few writes a part may make go through
accessors too: an object's free joint (`free_joint`), a marker (`mocap_pos`), and the models
the copies run on (`set_models`, for per-copy terrain).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol, runtime_checkable

import mujoco
import numpy as np

MAX_SPEED = 100.0
"""m/s or rad/s: a copy with any velocity above it has blown up (the environment ends it).
MuJoCo itself only warns at 1e10; below that a body can spin up in the air (Euler integration
does not keep its angular momentum) and be flung tens of km in one step, a forward reward of
millions. Trainings that do not blow up stay under 50 (the largest |qvel| over 150k steps of each
of four bodies of a demo run: 32-49), as in Gym's Hopper, whose healthy state is bounded by 100."""


class FreeJoint(NamedTuple):
    """A free body's state in every copy: live (N, 7) position + quaternion, (N, 6) velocity
    (linear in the world frame, then angular in the body's own frame: MuJoCo's qvel), and its
    (N, 3, 3) orientation, columns the body's axes in the world (derived from the state: current
    after each step and each placement, read-only)."""

    qpos: np.ndarray
    qvel: np.ndarray
    rot: np.ndarray


@runtime_checkable
class EnvView(Protocol):
    """The environment as its task's parts see it."""

    @property
    def num_envs(self) -> int:
        """N, the number of copies."""
        ...

    @property
    def all(self) -> np.ndarray:
        """The ids of every copy; ``ids is env.all`` marks a call for all copies (no selection)."""
        ...

    @property
    def rng(self) -> np.random.Generator:
        """The run's random generator (replaced by every seeded reset: read it when drawing)."""
        ...

    @property
    def control_dt(self) -> float:
        """s per control step: the model's timestep x the environment's frame skip."""
        ...

    @property
    def model(self) -> mujoco.MjModel:
        """The compiled model of the body in its task (shared by the copies unless set)."""
        ...

    @property
    def head_pos(self) -> np.ndarray:
        """(N, 3) head centre in the world."""
        ...

    @property
    def prev_head(self) -> np.ndarray:
        """(N, 3) head centre before the last control step (at placement: where it was put)."""
        ...

    @property
    def head_vel(self) -> np.ndarray:
        """(N, 3) head linear velocity in the world."""
        ...

    @property
    def head_rot(self) -> np.ndarray:
        """(N, 3, 3) head orientation: columns are the head's axes in the world."""
        ...

    @property
    def ctrl(self) -> np.ndarray:
        """(N, A) the last actions, clipped to [-1, 1]."""
        ...

    @property
    def action(self) -> np.ndarray:
        """(N, A) the last actions as the policy gave them (unclipped)."""
        ...

    @property
    def yaw(self) -> np.ndarray:
        """(N,) heading: the head's x axis projected on the ground, from +x towards +y."""
        ...

    def to_head_frame(self, vectors: np.ndarray) -> np.ndarray:
        """World vectors (N, 3) expressed in each copy's head frame."""
        ...

    def agent_points(self) -> np.ndarray:
        """(N, P, 3) the head centre and bottom and every limb's mid and end sites, in the
        world."""
        ...

    def free_joint(self, name: str) -> FreeJoint:
        """Live state views of the free joint ``name`` (writable: parts place objects)."""
        ...

    def mocap_pos(self, body: str) -> np.ndarray:
        """Live (N, 3) writable position of the mocap body ``body``."""
        ...

    def set_models(self, models: Sequence[mujoco.MjModel]) -> None:
        """Run copy i on ``models[i]`` (copies of `model` with other asset data, e.g. terrain)."""
        ...
