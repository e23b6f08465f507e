"""Flat stretches on a plane, obstacles on the heightfield, as the released code built them.

The released code made VT's and MVT's flat segments of box geoms and only its obstacles of
heightfield geoms. On a heightfield every grid triangle under a geom is a contact of its own: a
capsule lying on flat heightfield makes up to 8 contacts where a plane or a box makes 2, MVT's
box 49 where a plane makes 4, and the triangles' edges turn resting bodies. derl's copies share
one model layout, so their obstacles cannot move between episodes; instead every copy's world
has both grounds, an invisible plane at the flats' height (z = 0) and the heightfield, and each
body collides with one of them: with the plane while nothing of it can reach an obstacle within
the next control step, else with the heightfield (`FlatGround.choose`, before every step). Flat
heightfield and plane coincide, so the switch moves nothing; a body astride a seam touches the
heightfield where the released code's would touch both.

Bodies are told apart by their collision bits: the agent's geoms have MuJoCo's default
``contype`` 1 (`AGENT_BIT`), objects such as MVT's box `OBJECT_BIT`; the two grounds have
``contype`` 0 and the bits of the bodies they carry as ``conaffinity``.
"""

from __future__ import annotations

import mujoco
import numpy as np

from derl.envs.terrain_stack import HFIELD_NAME, TerrainStack
from derl.envs.view import EnvView

AGENT_BIT = 1
OBJECT_BIT = 2
BITS = AGENT_BIT | OBJECT_BIT
PLANE_NAME = "flat_ground"
TRAVEL = 0.5
"""m a body's root may move in one control step (25 m/s), beyond which it may reach an obstacle
while it still collides with the plane."""


def add_plane(spec: mujoco.MjSpec) -> None:
    """Add the invisible plane at z = 0, as large as the heightfield (`add_hfield`), that
    bodies over flat stretches collide with. Both grounds carry every body until `FlatGround`
    chooses: MuJoCo leaves a geom that collides with nothing when compiled out of its collision
    tree for good."""
    heightfield = spec.geom(HFIELD_NAME)
    heightfield.contype, heightfield.conaffinity = 0, BITS
    half_x, half_y = spec.hfield(HFIELD_NAME).size[:2]
    spec.worldbody.add_geom(
        name=PLANE_NAME,
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[half_x, half_y, 0.1],
        rgba=[0, 0, 0, 0],
        group=3,
        contype=0,
        conaffinity=BITS,
        condim=heightfield.condim,
        friction=heightfield.friction,
    )


def reach(model: mujoco.MjModel, body: int) -> float:
    """m: no point of a geom of ``body`` or its descendants lies further than this from
    ``body``'s origin, whatever their joints' angles (a hinge turns a child about its anchor,
    which moves the child's origin by at most twice the anchor's offset)."""
    origin = {body: 0.0}
    furthest = 0.0
    for b in range(body, model.nbody):
        if b != body:
            parent = int(model.body_parentid[b])
            if parent not in origin:
                continue
            joints = slice(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
            swing = 2 * float(np.linalg.norm(model.jnt_pos[joints], axis=1).max(initial=0.0))
            origin[b] = origin[parent] + float(np.linalg.norm(model.body_pos[b])) + swing
        geoms = slice(model.body_geomadr[b], model.body_geomadr[b] + model.body_geomnum[b])
        extent = np.linalg.norm(model.geom_pos[geoms], axis=1) + model.geom_rbound[geoms]
        furthest = max(furthest, origin[b] + float(extent.max(initial=0.0)))
    return furthest


class FlatGround:
    """Which ground each body of each copy collides with, written into the copies' own models
    (`TerrainStack.models` of planned terrains, built with `add_hfield` and `add_plane`)."""

    def __init__(self, env: EnvView, terrains: TerrainStack) -> None:
        model = env.model
        self.terrains = terrains
        self.plane = model.geom(PLANE_NAME).id
        self.heightfield = model.geom(HFIELD_NAME).id
        head = model.body("head").id
        movers = [("root", reach(model, head), AGENT_BIT)]
        for j in range(model.njnt):
            name = model.joint(j).name
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE and name != "root":
                movers.append((name, reach(model, int(model.jnt_bodyid[j])), OBJECT_BIT))
        self._x = [env.free_joint(name).qpos[:, 0] for name, _, _ in movers]
        self._reach = np.array([[r + TRAVEL] for _, r, _ in movers])
        self._bits = np.array([bit for _, _, bit in movers])
        self.on_plane = np.full(env.num_envs, -1)
        """Per copy, the bits of the bodies that collide with the plane (the rest: with the
        heightfield), as its model says (-1: both grounds carry every body, as compiled)."""

    def choose(self, ids: np.ndarray) -> None:
        """Give each body of copies ``ids`` the ground it can touch in the next control step."""
        x = np.array([view[ids] for view in self._x])  # (bodies, len(ids))
        bits = self._bits @ self.terrains.level(x - self._reach, x + self._reach, ids)
        models = self.terrains.models
        for k in np.flatnonzero(bits != self.on_plane[ids]).tolist():
            i, on_plane = int(ids[k]), int(bits[k])
            models[i].geom_conaffinity[self.plane] = on_plane
            models[i].geom_conaffinity[self.heightfield] = BITS & ~on_plane
            self.on_plane[i] = on_plane
