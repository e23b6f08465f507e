"""Compile a genome into a MuJoCo model with `mujoco.MjSpec`: bodies, motors, sensors, exclusions.

`agent_spec` builds the body alone (a free-floating head with its limb tree), the piece every
environment attaches to its world. `standalone_spec` puts it on a floor under a sky, so the saved
MJCF opens in MuJoCo's viewer as it is. Names: body/geom ``head`` and ``limb<id>`` (a mirror twin
is ``limb<id>_mirror``); sites ``<part>_mid``, ``<part>_end``, ``<part>_tip``, ``<part>_touch`` and
``head_imu``; hinges and their motors ``<part>_x`` / ``<part>_y``; sensors ``head_accel``,
``head_gyro``, ``head_vel``, ``<part>_touch`` and ``<part>_end_pos`` (end site in the head's body
frame; the environments observe its x and y).
"""

from __future__ import annotations

import mujoco
import numpy as np

from derl.unimal.genome import Genome
from derl.unimal.geometry import LimbPart, layout
from derl.unimal.scenery import add_scenery
from derl.unimal.space import HEAD_RADIUS, LIMB_RADIUS

TIMESTEP = 0.005
FRICTION = (0.7, 0.1, 0.1)
JOINT_DAMPING = 1.0
JOINT_STIFFNESS = 1.0
JOINT_ARMATURE = 1.0
JOINT_SOLIMPLIMIT = (0.0, 0.99, 0.01, 0.5, 2.0)
TOUCH_MARGIN = 0.01
HEAD_RGBA = (0.85, 0.45, 0.2, 1.0)
LIMB_RGBA = (0.25, 0.45, 0.75, 1.0)
SITE_SIZE = 0.01
FLOOR_OFFSET = 0.2
"""m between a body's lowest point (`rest_height`) and the ground where it spawns (the released
code's `BODY.FLOOR_OFFSET`): every environment drops it from there."""


def agent_spec(genome: Genome, head_height: float | None = None) -> mujoco.MjSpec:
    """The body alone, head centre at `head_height` (default: lowest point at z=0)."""
    parts = layout(genome)
    if head_height is None:
        head_height = rest_height(parts)
    spec = mujoco.MjSpec()
    spec.modelname = "unimal"
    spec.compiler.degree = False
    spec.option.timestep = TIMESTEP
    head = spec.worldbody.add_body(name="head", pos=[0.0, 0.0, head_height])
    head.add_freejoint(name="root")
    _capsule_or_sphere(
        head,
        name="head",
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[HEAD_RADIUS, 0, 0],
        density=genome.head_density,
        rgba=HEAD_RGBA,
    )
    head.add_site(name="head_imu", size=[SITE_SIZE] * 3)
    head.add_site(
        name="head_touch",
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[HEAD_RADIUS + TOUCH_MARGIN, 0, 0],
        rgba=[0, 0, 0, 0],
    )
    bodies = {"head": head}
    for part in parts:
        bodies[part.name] = _add_limb(spec, bodies[part.parent], part, genome.limb_density)
    _add_sensors(spec, parts)
    for first, second in excluded_pairs(genome, parts):
        spec.add_exclude(bodyname1=first, bodyname2=second)
    return spec


def standalone_spec(genome: Genome, clearance: float = 0.05) -> mujoco.MjSpec:
    """The body standing `clearance` above a floor, with a sky and lights: a complete MJCF scene
    (for pictures and the saved MJCF; `FLOOR_OFFSET` where it starts as in the environments)."""
    spec = agent_spec(genome, head_height=rest_height(layout(genome)) + clearance)
    material = add_scenery(spec, spec.body("head"))
    spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[50, 50, 0.1],
        material=material,
        condim=3,
        friction=list(FRICTION),
    )
    return spec


def to_mjcf(genome: Genome) -> str:
    """The standalone scene as MJCF XML text."""
    spec = standalone_spec(genome)
    spec.compile()
    return spec.to_xml()


def rest_height(parts: list[LimbPart]) -> float:
    """Height of the head centre above the body's lowest point at rest, as the released code
    measures it (`SymmetricUnimal.set_head_pos`, its `btm_pos` sites): the lowest limb tip on its
    limb's axis (the capsule's end along the axis), or the head's bottom. A limb pointing 45
    degrees down reaches r (1 - cos 45) = 1.5 cm below its tip."""
    return float(-min([-HEAD_RADIUS, *(p.origin[2] + p.tip[2] for p in parts)]))


def stand_height(genome: Genome) -> float:
    """The head's height above the ground that the environments take as the body's resting
    height (it spawns `FLOOR_OFFSET` higher, and falls below a fraction of it): the genome's
    `stand_height` where set (the released code's `delete_limb` keeps the parent's), else its
    own `rest_height`."""
    if genome.stand_height is not None:
        return genome.stand_height
    return rest_height(layout(genome))


def excluded_pairs(genome: Genome, parts: list[LimbPart]) -> list[tuple[str, str]]:
    """Body pairs whose contacts are excluded: parent-child, and twins grown on one site."""
    pairs = [(part.parent, part.name) for part in parts]
    for part in parts:
        if part.twin and genome.is_sagittal(part.limb.parent):
            pairs.append((part.name.removesuffix("_mirror"), part.name))
    return pairs


def _capsule_or_sphere(body: mujoco.MjsBody, **kwargs: object) -> mujoco.MjsGeom:
    return body.add_geom(condim=3, friction=list(FRICTION), **kwargs)


def _add_limb(
    spec: mujoco.MjSpec, parent: mujoco.MjsBody, part: LimbPart, density: float
) -> mujoco.MjsBody:
    body = parent.add_body(name=part.name, pos=part.pos.tolist())
    end = part.end.tolist()
    for joint, axis in zip(part.limb.joints, part.axes, strict=True):
        name = f"{part.name}_{joint.axis}"
        body.add_joint(
            name=name,
            type=mujoco.mjtJoint.mjJNT_HINGE,
            pos=(-LIMB_RADIUS * part.direction).tolist(),
            axis=axis.tolist(),
            range=np.deg2rad(joint.range).tolist(),
            limited=mujoco.mjtLimited.mjLIMITED_TRUE,
            damping=JOINT_DAMPING,
            stiffness=JOINT_STIFFNESS,
            armature=JOINT_ARMATURE,
            solimp_limit=list(JOINT_SOLIMPLIMIT),
        )
        spec.add_actuator(
            name=name,
            target=name,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            gear=[joint.gear, 0, 0, 0, 0, 0],
            ctrllimited=mujoco.mjtLimited.mjLIMITED_TRUE,
            ctrlrange=[-1.0, 1.0],
        )
    _capsule_or_sphere(
        body,
        name=part.name,
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        fromto=[0, 0, 0, *end],
        size=[LIMB_RADIUS, 0, 0],
        density=density,
        rgba=LIMB_RGBA,
    )
    for site, pos in (("mid", part.mid), ("end", part.end), ("tip", part.tip)):
        body.add_site(name=f"{part.name}_{site}", pos=pos.tolist(), size=[SITE_SIZE] * 3)
    body.add_site(
        name=f"{part.name}_touch",
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        fromto=[0, 0, 0, *end],
        size=[LIMB_RADIUS + TOUCH_MARGIN, 0, 0],
        rgba=[0, 0, 0, 0],
    )
    return body


def _add_sensors(spec: mujoco.MjSpec, parts: list[LimbPart]) -> None:
    site = mujoco.mjtObj.mjOBJ_SITE
    for kind, name in (
        (mujoco.mjtSensor.mjSENS_ACCELEROMETER, "head_accel"),
        (mujoco.mjtSensor.mjSENS_GYRO, "head_gyro"),
        (mujoco.mjtSensor.mjSENS_VELOCIMETER, "head_vel"),
    ):
        spec.add_sensor(name=name, type=kind, objtype=site, objname="head_imu")
    for part_name in ["head", *(p.name for p in parts)]:
        spec.add_sensor(
            name=f"{part_name}_touch",
            type=mujoco.mjtSensor.mjSENS_TOUCH,
            objtype=site,
            objname=f"{part_name}_touch",
        )
    for part in parts:
        spec.add_sensor(
            name=f"{part.name}_end_pos",
            type=mujoco.mjtSensor.mjSENS_FRAMEPOS,
            objtype=site,
            objname=f"{part.name}_end",
            reftype=mujoco.mjtObj.mjOBJ_XBODY,
            refname="head",
        )
