"""The set a clip is filmed on: the environment's world compiled again with scenery, posed each
frame as copy 0 of the environment is.

The environment's own model carries nothing visual. `FilmSet` builds the same world (the body, the
task's arena and props) with the scenery of `derl.unimal.scenery` (sky, checkered ground, a sun
that follows the body), a pole over each object and goal, and copies copy 0's positions into it:
the physics stays the environment's. A heightfield is drawn twice: in full detail in a patch of
`PATCH` metres around the body filmed, cut from copy 0's terrain and moved as the body walks, and
whole, coarsely (every `COARSE_STEP`-th vertex; under the patch a running minimum, so that it
lies below the detailed surface there, and 2 cm lower). Renderers without a GPU (Mesa's
llvmpipe) spend 0.6 s a frame on a whole 100 m VT terrain at its 0.1 m resolution.
"""

from __future__ import annotations

import mujoco
import numpy as np
from scipy import ndimage

from derl.envs.batched import UnimalEnv
from derl.envs.objects import CarriedObject, GoalPoint
from derl.envs.terrain_stack import HFIELD_NAME, TerrainStack
from derl.unimal.mjcf import agent_spec
from derl.unimal.scenery import GROUND_SQUARE, add_scenery

FLOOR = "floor"
FAR_TERRAIN = "terrain_far"
PATCH = (24.0, 16.0)
"""Size (x, y) of the detailed heightfield patch around the body filmed, m."""
PATCH_AHEAD = 6.0
"""The patch's centre lies this far ahead (+x) of the target: bodies walk along +x."""
PATCH_SLACK = 3.0
"""The patch is moved when its centre is this far from where it should be, m."""
COARSE_STEP = 4
"""The whole heightfield is drawn with every this-many-th vertex (0.4 m for VT's 0.1 m)."""
COARSE_DROP = 0.02
"""The coarse heightfield lies this much lower, m: where the patch is, the patch is seen."""
HAZE = (20.0, 60.0)
"""Haze from this distance to full at that one, m: the ground's far edge fades into the sky."""
PLANE_GRID = 2.0
"""A plane is drawn in squares of this side, m (the environment's 0.1 m made 2 million squares
of FT's floor; a plane's third size is for drawing only)."""
GOAL_RGBA = (0.85, 0.15, 0.15, 1.0)
OBJECT_RGBA = (0.95, 0.75, 0.1, 1.0)
POLE = 3.0
"""Height of the pole over an object or a goal, m; a ball of `FLAG` m radius tops it."""
FLAG = 0.3
REACHED = 1.0
"""The body has reached its object when its head is this close to the object's side, m."""


class FilmSet:
    """The world of `env` dressed for filming (`model`), posed as copy 0 by `pose`."""

    def __init__(self, env: UnimalEnv) -> None:
        self.env = env
        self.terrains: TerrainStack | None = env.task.arena.terrains
        self.objects = [part for part in env.task.props if isinstance(part, CarriedObject)]
        self.goals = [part for part in env.task.props if isinstance(part, GoalPoint)]
        self.model = self._compile()
        self.data = mujoco.MjData(self.model)
        self.source = mujoco.MjData(env.model)
        self.root = int(env.model.jnt_qposadr[env.model.joint("root").id])
        self.patch_at = np.full(2, np.inf)
        self.terrain_version = -1
        self.uploads: list[int] = []
        """Heightfields changed since the renderer last had them (`take_uploads`)."""

    def _compile(self) -> mujoco.MjModel:
        env = self.env
        spec = agent_spec(env.genome, head_height=env.rest_height + env.config.spawn_clearance)
        env.task.build(spec)
        material = add_scenery(spec, spec.body("head"))
        for name in (FLOOR, HFIELD_NAME):
            geom = spec.geom(name)
            if geom is not None:
                geom.material, geom.rgba = material, [0.5, 0.5, 0.5, 1.0]  # the material's colour
                if geom.type == mujoco.mjtGeom.mjGEOM_PLANE:
                    geom.size[2] = PLANE_GRID
        goal = spec.body("goal")  # a carried object's goal marker
        if goal is not None:
            _add_pole(goal, GOAL_RGBA)
        for k in range(len(self.objects)):  # a pole over each object, upright whatever it does
            _add_pole(spec.worldbody.add_body(name=f"object_marker{k}", mocap=True), OBJECT_RGBA)
        for k in range(len(self.goals)):  # a goal for the head has no marker of its own
            marker = spec.worldbody.add_body(name=f"goal_marker{k}", mocap=True)
            marker.add_geom(
                type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                size=[0.3, 0.01, 0],
                rgba=list(GOAL_RGBA),
                contype=0,
                conaffinity=0,
            )
            _add_pole(marker, GOAL_RGBA)
        if self.terrains is not None:
            self._add_terrain_views(spec, material)
        model = spec.compile()
        extent = model.stat.extent
        model.vis.map.fogstart, model.vis.map.fogend = HAZE[0] / extent, HAZE[1] / extent
        model.vis.map.znear, model.vis.map.zfar = 0.05 / extent, 2 * HAZE[1] / extent
        model.vis.quality.shadowsize = 1024
        return model

    def _add_terrain_views(self, spec: mujoco.MjSpec, material: str) -> None:
        """Turn the heightfield into the detailed patch, and add the coarse whole one. The
        patch moves in whole periods of the checker relative to the coarse one, so that the
        ground's squares never jump."""
        assert self.terrains is not None
        config = self.terrains.config
        grid = np.array(config.grid_shape[::-1])  # vertices along (x, y)
        cells = np.minimum(2 * np.round(np.array(PATCH) / config.resolution / 2), grid - 1)
        self.patch_shape = (int(cells[1]) + 1, int(cells[0]) + 1)  # (rows, cols)
        patch = spec.hfield(HFIELD_NAME)
        _shape_hfield(patch, self.patch_shape, config.resolution)
        coarse = (grid - 1) // COARSE_STEP
        far = spec.add_hfield(name=FAR_TERRAIN, size=list(patch.size))
        _shape_hfield(far, (coarse[1] + 1, coarse[0] + 1), config.resolution * COARSE_STEP)
        self.period = round(2 * GROUND_SQUARE / config.resolution)  # the checker's, in cells
        self.phase = (coarse * COARSE_STEP // 2 - cells.astype(int) // 2) % self.period
        corner = np.array([-config.size_x / 2, -config.size_y / 2])
        spec.worldbody.add_geom(
            name=FAR_TERRAIN,
            type=mujoco.mjtGeom.mjGEOM_HFIELD,
            hfieldname=FAR_TERRAIN,
            pos=[*(corner + coarse * COARSE_STEP * config.resolution / 2), -COARSE_DROP],
            material=material,
            contype=0,
            conaffinity=0,
        )

    def pose(self, target: np.ndarray | None = None) -> np.ndarray:
        """Pose the set as copy 0 now (the detailed terrain around `target`, default: the head);
        the head's position."""
        self.env.batch.get_data(0, self.source)
        data = self.data
        data.qpos[:] = self.source.qpos
        carried = self.env.model.nmocap  # then the object and goal markers of this set
        data.mocap_pos[:carried] = self.source.mocap_pos
        data.mocap_quat[:carried] = self.source.mocap_quat
        for k, obj in enumerate(self.objects):
            data.mocap_pos[carried + k] = obj.position[0] + [0.0, 0.0, obj.half]
        for k, goal in enumerate(self.goals, carried + len(self.objects)):
            data.mocap_pos[k] = goal.goal[0]
        head = self.source.qpos[self.root : self.root + 3].copy()
        if self.terrains is not None:
            self._cut_terrain(head if target is None else target)
        mujoco.mj_kinematics(self.model, data)
        mujoco.mj_comPos(self.model, data)
        mujoco.mj_camlight(self.model, data)
        if self.terrains is not None:  # a static geom: kinematics keeps its first position
            patch = self.model.geom(HFIELD_NAME).id
            data.geom_xpos[patch] = self.model.geom_pos[patch]
        return head

    def focus(self, head: np.ndarray) -> np.ndarray | None:
        """Where copy 0's body is to go: its object until it reaches it, then the object's goal;
        its goal; None for a walk along +x."""
        for obj in self.objects:
            box = obj.position[0]
            if np.linalg.norm(box[:2] - head[:2]) > REACHED + obj.half:
                return box.copy()
            return obj.goal[0].copy()
        for goal in self.goals:
            return goal.goal[0].copy()
        return None

    def marks(self, head: np.ndarray) -> np.ndarray:
        """(K, 3) what a clip is to show besides the body, the most wanted first: where the body
        is to go (`focus`) and the ball atop its pole, then each other object and goal, then the
        balls atop theirs."""
        places = [obj.position[0] for obj in self.objects]
        places += [obj.goal[0] for obj in self.objects] + [goal.goal[0] for goal in self.goals]
        focus = self.focus(head)
        places.sort(key=lambda place: focus is None or not np.array_equal(place, focus))
        bases = np.array(places).reshape(-1, 3)
        balls = bases + np.array([0.0, 0.0, POLE + FLAG])
        return np.concatenate([bases[:1], balls[:1], bases[1:], balls[1:]])

    def _cut_terrain(self, target: np.ndarray) -> None:
        """The patch around `target` and the coarse terrain around it, when copy 0's terrain
        is new or the target has gone `PATCH_SLACK` from the patch."""
        terrains = self.terrains
        assert terrains is not None
        want = target[:2] + np.array([PATCH_AHEAD, 0.0])
        new = terrains.generated != self.terrain_version
        if not new and np.all(np.abs(want - self.patch_at) < PATCH_SLACK):
            return
        config, shape = terrains.config, terrains.config.grid_shape
        heights = terrains.hfield_heights(0)
        if new:  # every coarse vertex, and the running minimum around it
            window = 2 * COARSE_STEP + 3  # a coarse cell's vertices and the fine ones between
            low = ndimage.minimum_filter(heights, size=window, mode="nearest")
            self.coarse = heights[::COARSE_STEP, ::COARSE_STEP].copy()
            self.coarse_low = low[::COARSE_STEP, ::COARSE_STEP]
        rows, cols = self.patch_shape
        corner = np.array([-config.size_x / 2, -config.size_y / 2])
        half = (np.array([cols, rows]) - 1) / 2
        first = (want - corner) / config.resolution - half  # the patch's first (column, row)
        last = np.array([shape[1] - cols, shape[0] - rows])
        col, row = (_in_phase(first[k], last[k], int(self.phase[k]), self.period) for k in range(2))
        self._write(HFIELD_NAME, heights[row : row + rows, col : col + cols])
        patch = self.model.geom(HFIELD_NAME).id
        self.model.geom_pos[patch, :2] = corner + (np.array([col, row]) + half) * config.resolution
        # under the patch, and one coarse vertex around it, the coarse terrain is the minimum:
        # every coarse triangle over the patch lies below the detailed surface
        far = self.coarse.copy()
        (r0, c0), (r1, c1) = ((row, col), (row + rows - 1, col + cols - 1))
        box = np.s_[
            max(r0 // COARSE_STEP - 1, 0) : -(-r1 // COARSE_STEP) + 2,
            max(c0 // COARSE_STEP - 1, 0) : -(-c1 // COARSE_STEP) + 2,
        ]
        far[box] = self.coarse_low[box]
        self._write(FAR_TERRAIN, far)
        self.patch_at, self.terrain_version = want, terrains.generated

    def _write(self, name: str, heights: np.ndarray) -> None:
        hfield = self.model.hfield(name)
        start = int(hfield.adr[0])
        self.model.hfield_data[start : start + heights.size] = heights.ravel()
        self.uploads.append(hfield.id)

    def take_uploads(self) -> list[int]:
        """The heightfields to send to the renderer again (each once)."""
        uploads, self.uploads = sorted(set(self.uploads)), []
        return uploads


def _in_phase(first: float, last: int, phase: int, period: int) -> int:
    """The index in [0, last] nearest `first` that is `phase` (in [0, period)) modulo `period`
    (the nearest index, when no such one is in range)."""
    most = (last - phase) // period  # indices phase + k period, k = 0 .. most
    if most < 0:
        return int(np.clip(round(first), 0, last))
    return phase + period * int(np.clip(round((first - phase) / period), 0, most))


def _add_pole(body: mujoco.MjsBody, rgba: tuple[float, ...]) -> None:
    """A pole topped by a ball standing on `body`, seen from afar; visual only."""
    for kind, size, height in (
        (mujoco.mjtGeom.mjGEOM_CYLINDER, [0.08, POLE / 2, 0], POLE / 2),
        (mujoco.mjtGeom.mjGEOM_SPHERE, [FLAG, 0, 0], POLE + FLAG),
    ):
        body.add_geom(type=kind, size=size, pos=[0, 0, height], rgba=list(rgba), contype=0,
                      conaffinity=0)  # fmt: skip


def _shape_hfield(hfield: mujoco.MjsHField, shape: tuple[int, int], spacing: float) -> None:
    """Give `hfield` `shape` (rows, columns) vertices `spacing` m apart, all at height 0."""
    rows, cols = shape
    hfield.nrow, hfield.ncol = rows, cols
    hfield.size = [(cols - 1) * spacing / 2, (rows - 1) * spacing / 2, *hfield.size[2:]]
    hfield.userdata = np.zeros(rows * cols).tolist()
