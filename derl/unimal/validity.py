"""The physical validity of a body: it compiles, its centre of mass lies on the sagittal plane,
and at rest no two bodies touch except a parent and its child, or twins grown on one site."""

from __future__ import annotations

import mujoco

from derl.unimal.genome import Genome
from derl.unimal.mjcf import agent_spec

COM_TOLERANCE = 1e-9


class InvalidBody(ValueError):
    """A genome whose body cannot exist: the message says why."""


def check_body(genome: Genome) -> None:
    """Raise `InvalidBody` unless the body is physically valid (about 1 ms)."""
    try:
        model = agent_spec(genome).compile()
    except ValueError as error:  # MuJoCo's compiler reports problems as ValueError
        raise InvalidBody(f"MuJoCo cannot compile the body: {error}") from error
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    com_y = float(data.subtree_com[model.body("head").id, 1])
    if abs(com_y) >= COM_TOLERANCE:
        raise InvalidBody(f"centre of mass off the sagittal plane (y = {com_y:.3g})")
    if data.ncon:
        contacts = sorted(
            {
                tuple(sorted((_body_name(model, c.geom1), _body_name(model, c.geom2))))
                for c in data.contact[: data.ncon]
            }
        )
        listed = ", ".join(f"{a}-{b}" for a, b in contacts)
        raise InvalidBody(f"self-intersection at rest: {listed}")


def _body_name(model: mujoco.MjModel, geom: int) -> str:
    return model.body(model.geom_bodyid[geom]).name
