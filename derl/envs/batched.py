"""N copies of one body in one task, stepped together in C by `mujoco.batch.Batch`.

The model is compiled once per body and task; terrain, objects and goals change per episode by
writing into the model copies and the state, never by recompiling. A body spawns with its head
`rest_height` + `FLOOR_OFFSET` (0.2 m) above the ground and drops: its lowest point 0.2 m up,
unless its genome keeps its parent's stand height (`derl.unimal.mjcf.stand_height`). Observations,
rewards and endings are numpy operations over all copies at once. Each step applies the actions
(clipped to [-1, 1]) for 4 physics steps of 5 ms (50 Hz control); an episode lasts 1000 control
steps unless the head falls below half `rest_height` (or the task's `fall_ratio`) above the
ground of the grid cell it is in (`Arena.fall_ground`, the released code's), leaves the
arena, the task is achieved, or the physics goes unstable (MuJoCo error, warning, non-finite
state, or a speed no body reaches: that copy ends, its step earns nothing, and it is counted).
Finished copies reset themselves inside `step`, which satisfies `derl.rl.BatchedEnv`.
"""

from __future__ import annotations

import operator
import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import reduce

import mujoco
import mujoco.batch
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from derl.envs.task import Arrays, Task
from derl.envs.view import MAX_SPEED, FreeJoint
from derl.unimal import Genome, agent_spec
from derl.unimal.mjcf import FLOOR_OFFSET, TIMESTEP, stand_height
from derl.unimal.space import HEAD_RADIUS

ARENA_MARGIN = 1.0  # m: a copy ends this close to the arena's edge

SLEEPERS = {
    int(policy)
    for policy in (
        mujoco.mjtSleepPolicy.mjSLEEP_AUTO_ALLOWED,
        mujoco.mjtSleepPolicy.mjSLEEP_ALLOWED,
        mujoco.mjtSleepPolicy.mjSLEEP_INIT,
    )
}
"""Sleep policies of kinematic trees that may sleep (MuJoCo gives every tree that no actuator
moves `mjSLEEP_AUTO_ALLOWED`)."""


class EnvConfig(BaseModel):
    """How the copies are simulated; defaults are the paper's. `control_dt`, the physics
    timestep (`derl.unimal.mjcf.TIMESTEP`) x `frame_skip`, is the one control step every part
    reads (through `EnvView.control_dt`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    num_envs: int = Field(32, ge=1)
    nthread: int = Field(1, ge=1)
    episode_steps: int = Field(1000, ge=1)
    frame_skip: int = Field(4, ge=1)
    reset_noise: float = Field(0.005, ge=0)
    spawn_clearance: float = Field(FLOOR_OFFSET, ge=0)
    fall_ratio: float = Field(0.5, ge=0, le=1)
    sleep: bool = False
    """MuJoCo's sleeping for the bodies allowed to sleep (those no actuator moves: MVT's box): a
    body whose speed stays under ``sleep_tolerance`` for 10 physics steps freezes, its contacts
    with the ground skipped, until the agent touches it or a reset moves it (MVT's physics 2-3x
    faster). Off by default: the released code simulated the box throughout, and an effect of
    sleeping on fitness at the paper's budget is not ruled out (docs/fidelity.md, "Objects at
    rest"); an opt-in speed switch."""

    @property
    def control_dt(self) -> float:
        """s per control step (the paper's 20 ms: 4 x 5 ms)."""
        return TIMESTEP * self.frame_skip

    def fitness_bound(self, task: Task) -> float:
        """The largest |fitness| `task` allows in episodes simulated so (`Task.fitness_bound`)."""
        return task.fitness_bound(self.control_dt, self.episode_steps)


@dataclass(frozen=True)
class StepResult:
    """One batched step: the fields of `derl.rl.StepResult`, and the observations the finished
    copies ended with (`final_obs`, for `derl.envs.gym_env`)."""

    obs: Arrays
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    final_obs: Arrays
    components: Arrays


class UnimalEnv:
    """A batch of copies of one UNIMAL in one task; the task's parts see it as an `EnvView`."""

    def __init__(
        self, genome: Genome, task: Task, config: EnvConfig | None = None, seed: int = 0
    ) -> None:
        self.genome = genome
        self.task = task
        self.config = config or EnvConfig()
        self.rest_height = stand_height(genome)  # its own, or the one its genome keeps
        spec = agent_spec(genome, head_height=self.rest_height + self.config.spawn_clearance)
        task.build(spec)
        self.model = spec.compile()
        if self.config.sleep and SLEEPERS.intersection(self.model.tree_sleep_policy.tolist()):
            self.model.opt.enableflags |= mujoco.mjtEnableBit.mjENBL_SLEEP
        self.batch = mujoco.batch.Batch(
            self.model, self.config.num_envs, nthread=self.config.nthread, persistent=True
        )
        self.rng = np.random.default_rng(seed)
        self._index_model()
        self._bind()
        task.bind(self)
        self.batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
        # Each copy's state rows as `Batch.reset` leaves them: `_reset` writes them directly.
        self._initial_state = self.batch.state.copy()
        # MuJoCo's sleep countdowns are not part of the state (and read-only here): with sleeping
        # on, a reset copy is reset whole, so an episode does not depend on the one before
        self._sleeps = bool(self.model.opt.enableflags & mujoco.mjtEnableBit.mjENBL_SLEEP)
        self.all = np.arange(self.num_envs)
        fall_ratio = self.config.fall_ratio if task.fall_ratio is None else task.fall_ratio
        self.fall_height = fall_ratio * self.rest_height  # head below it: fallen
        self.arena_inside = np.array(task.arena.half) - ARENA_MARGIN  # head beyond: off the arena
        self.steps = np.zeros(self.num_envs, dtype=np.int64)
        self.unstable_count = 0
        self.constraint_rows = 0
        """MuJoCo's constraint rows (contacts, limits) at the end of each control step, summed over
        the copies and the steps: a count of the solver's work (the cluster timing's cost)."""
        self.physics_s = 0.0
        """Seconds spent in MuJoCo (the steps, and the forward passes of copies reset)."""
        self._obs_spaces = {"proprioception": self._proprioception(self.all).shape[1]}
        self._obs_spaces.update(task.obs_spaces())

    # --- the BatchedEnv interface -------------------------------------------------------------

    @property
    def control_dt(self) -> float:
        return self.config.control_dt

    @property
    def num_envs(self) -> int:
        return self.config.num_envs

    @property
    def obs_spaces(self) -> dict[str, int]:
        return dict(self._obs_spaces)

    @property
    def action_dim(self) -> int:
        return self.model.nu

    def reset(self, seed: int) -> Arrays:
        """Start a new episode in every copy; deterministic for a given seed."""
        self.rng = np.random.default_rng(seed)
        self.task.start()
        return self._reset(self.all)

    def step(self, actions: np.ndarray) -> StepResult:
        """Apply (N, A) actions for one control step: MuJoCo gets them clipped to [-1, 1], the
        control cost is on them as given (the released code's)."""
        self.action = actions
        # np.clip(actions, -1, 1) without its Python wrappers (ufunc calls here and below)
        np.minimum(np.maximum(actions, -1.0, out=self.ctrl), 1.0, out=self.ctrl)
        np.copyto(self.prev_head, self.head_pos)
        warnings_before = np.add.reduce(self._warning_counts, axis=1)
        failed = None
        start = time.perf_counter()
        try:
            self.batch.step(nstep=self.config.frame_skip, stage=mujoco.mjtStage.mjSTAGE_VEL)
        except mujoco.batch.SimulationError as error:
            failed = error.ids
        self.physics_s += time.perf_counter() - start
        self.constraint_rows += int(np.add.reduce(self._nefc))
        unstable = self._unstable(warnings_before, failed)
        unstable_count = int(np.count_nonzero(unstable))
        self.unstable_count += unstable_count
        self.steps += 1
        terms = self.task.step(self)
        components = {**terms, **self.task.metric_values(terms)}
        components["energy"] = np.abs(self.ctrl) @ self.gear
        if unstable_count:
            for values in components.values():
                values[unstable] = 0.0
        reward = reduce(operator.add, terms.values()) if terms else np.zeros(self.num_envs)
        terminated = self._fallen()
        terminated |= unstable
        terminated |= self._off_arena()
        if self.task.success is not None:
            terminated |= self.task.success(self)
        truncated = self.steps >= self.config.episode_steps  # terminated or not (the code's)
        obs = self._observe(self.all)
        final_obs = obs
        done = (terminated | truncated).nonzero()[0]
        if len(done):
            final_obs = {key: value.copy() for key, value in obs.items()}
            for key, value in self._reset(done).items():
                obs[key][done] = value
        return StepResult(obs, reward, terminated, truncated, final_obs, components)

    # --- what the task's parts see (`EnvView`) --------------------------------------------------

    # head_pos (N, 3): head centre in the world; head_vel (N, 3): its linear velocity; head_rot
    # (N, 3, 3): its orientation, columns are the head's axes in the world; prev_head (N, 3): the
    # head centre before the last step; ctrl (N, A): the clipped actions. Live views (`_bind`).
    # action (N, A): the actions as the last `step` was given them (unclipped).

    def to_head_frame(self, vectors: np.ndarray) -> np.ndarray:
        """World vectors (N, 3) expressed in each copy's head frame."""
        return np.einsum("nji,nj->ni", self.head_rot, vectors)

    @property
    def yaw(self) -> np.ndarray:
        """(N,) heading: the head's x axis projected on the ground, from +x towards +y."""
        rot = self.xmat[:, self.head]
        return np.arctan2(rot[:, 3], rot[:, 0])

    def agent_points(self) -> np.ndarray:
        """(N, P, 3) the head centre, the head's bottom (HEAD_RADIUS below its centre, along
        its z axis), and every limb's mid and end sites, in the world."""
        bottom = self.head_pos - HEAD_RADIUS * self.head_rot[:, :, 2]
        return np.concatenate([bottom[:, None], self.site_xpos[:, self.agent_sites]], axis=1)

    def free_joint(self, name: str) -> FreeJoint:
        """Live (N, 7) qpos, (N, 6) qvel and (N, 3, 3) orientation views of the free joint
        ``name``."""
        joint = self.model.joint(name)
        if joint.type[0] != mujoco.mjtJoint.mjJNT_FREE:
            raise ValueError(f"joint {name!r} is not a free joint")
        qpos, dof, body = int(joint.qposadr[0]), int(joint.dofadr[0]), int(joint.bodyid[0])
        rot = self.xmat[:, body].reshape(-1, 3, 3)
        rot.flags.writeable = False
        return FreeJoint(self.qpos[:, qpos : qpos + 7], self.qvel[:, dof : dof + 6], rot)

    def mocap_pos(self, body: str) -> np.ndarray:
        """Live (N, 3) position of the mocap body ``body``."""
        mocap = int(self.model.body(body).mocapid[0])
        if mocap < 0:
            raise ValueError(f"body {body!r} is not a mocap body")
        return self.batch.bind("mocap_pos")[:, mocap]

    def set_models(self, models: Sequence[mujoco.MjModel]) -> None:
        """Run copy i on ``models[i]``, a copy of `model` with its own asset data."""
        self.batch.set_models(models)

    # --- internals ----------------------------------------------------------------------------

    def _index_model(self) -> None:
        model = self.model
        root = model.joint("root")
        self.head = model.body("head").id
        self.root = int(root.qposadr[0])
        self.root_dof = int(root.dofadr[0])
        hinges = [j for j in range(model.njnt) if model.jnt_bodyid[j] != self.head]
        hinges = [j for j in hinges if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
        agent_bodies = self._agent_bodies()
        hinges = [j for j in hinges if model.jnt_bodyid[j] in agent_bodies]
        self.joint_qpos = np.array([model.jnt_qposadr[j] for j in hinges], dtype=np.intp)
        self.joint_dofs = np.array([model.jnt_dofadr[j] for j in hinges], dtype=np.intp)
        self.agent_qpos = np.concatenate([np.arange(self.root, self.root + 7), self.joint_qpos])
        self.agent_dofs = np.concatenate(
            [np.arange(self.root_dof, self.root_dof + 6), self.joint_dofs]
        )
        self.gear = model.actuator_gear[:, 0].copy()
        sensors = [model.sensor(i) for i in range(model.nsensor)]
        agent_sensors = [s for s in sensors if s.name.startswith(("head_", "limb"))]
        # a limb end's position in x and y of the head frame (the released code's `extremities`)
        self.sensor_index = np.concatenate(
            [
                np.arange(s.adr[0], s.adr[0] + (2 if s.name.endswith("_end_pos") else s.dim[0]))
                for s in agent_sensors
            ]
        )
        # what each proprioception column and each action is, by the body's part names (the
        # genome's limb ids): how an inherited controller finds its parent's (`derl.rl.inherit`)
        joints = [model.joint(j).name for j in hinges]
        self.proprioception_labels = (
            [f"qpos {name}" for name in joints]
            + [f"qvel root {k}" for k in range(6)]
            + [f"qvel {name}" for name in joints]
            + [
                f"sensor {s.name} {k}"
                for s in agent_sensors
                for k in range(2 if s.name.endswith("_end_pos") else s.dim[0])
            ]
        )
        self.action_labels = [model.actuator(a).name for a in range(model.nu)]
        sites = ["head_imu"] + [
            f"{model.body(b).name}_{kind}"
            for b in sorted(agent_bodies - {self.head})
            for kind in ("mid", "end")
        ]
        self.agent_sites = np.array([model.site(name).id for name in sites], dtype=np.intp)

    def _agent_bodies(self) -> set[int]:
        model = self.model
        bodies = {self.head}
        for body in range(self.head + 1, model.nbody):
            if model.body_parentid[body] in bodies:
                bodies.add(body)
        return bodies

    def _bind(self) -> None:
        batch = self.batch
        self.qpos = batch.bind("qpos")
        self.qvel = batch.bind("qvel")
        self.ctrl = batch.bind("ctrl")
        self.sensordata = batch.bind("sensordata")
        self.xmat = batch.bind("xmat")
        self.site_xpos = batch.bind("site_xpos")
        self._nefc = batch.bind("nefc")
        self.warnings = batch.warning  # (N, warning kinds, [last info, count])
        self._warning_counts = self.warnings[:, :, 1]
        # qpos and qvel: adjacent in the state rows, after the time (MuJoCo's state order)
        state = mujoco.mjtState
        start = mujoco.mj_stateSize(self.model, state.mjSTATE_TIME)
        end = mujoco.mj_stateSize(
            self.model, state.mjSTATE_TIME | state.mjSTATE_QPOS | state.mjSTATE_QVEL
        )
        self._qpos_qvel = batch.state[:, start:end]
        # the joints' qpos and the body's qvel, as columns of _qpos_qvel
        self._state_obs = np.concatenate([self.joint_qpos, self.model.nq + self.agent_dofs])
        self.head_pos = self.qpos[:, self.root : self.root + 3]
        self.head_vel = self.qvel[:, self.root_dof : self.root_dof + 3]
        self.head_rot = self.xmat[:, self.head].reshape(-1, 3, 3)
        self.prev_head = np.zeros((self.num_envs, 3))
        self.action = np.zeros((self.num_envs, self.model.nu))

    def _reset(self, ids: np.ndarray) -> Arrays:
        """New episodes for copies ``ids``; their first observations."""
        batch, config = self.batch, self.config
        if self._sleeps:  # 130 us against the copy's 14 us
            batch.reset(ids, stage=mujoco.mjtStage.mjSTAGE_NONE)
        else:
            batch.state[ids] = self._initial_state[ids]  # as batch.reset(ids), without checks
        self.task.reset(self, ids)
        n, noise = len(ids), config.reset_noise
        qpos = self.qpos[ids]
        spawn = qpos[:, self.root : self.root + 2]
        spawn[:] = self.task.spawn
        ground = self.task.arena.ground(spawn, ids)
        qpos[:, self.root + 2] = ground + self.rest_height + config.spawn_clearance
        qpos[:, self.root + 3 : self.root + 7] = self.task.arena.tilt  # upright on a slope
        qpos[:, self.agent_qpos] += self.rng.uniform(-noise, noise, (n, len(self.agent_qpos)))
        quat = qpos[:, self.root + 3 : self.root + 7]
        quat /= np.sqrt(np.square(quat).sum(axis=1, keepdims=True))
        self.qpos[ids] = qpos
        # the initial state has zero qvel and ctrl
        qvel_noise = self.rng.uniform(-noise, noise, (n, len(self.agent_dofs)))
        self.qvel[ids[:, None], self.agent_dofs] = qvel_noise
        self.task.posed(self, ids)
        start = time.perf_counter()
        # mj_forward, as the released code's reset (`set_state`): the first observation reads
        # the accelerometer and touch sensors at the spawn state
        batch.forward(ids, stage=mujoco.mjtStage.mjSTAGE_ACC)
        self.physics_s += time.perf_counter() - start
        self.steps[ids] = 0
        self.prev_head[ids] = self.head_pos[ids]
        self.task.placed(self, ids)
        return self._observe(ids)

    def _unstable(self, warnings_before: np.ndarray, failed: np.ndarray | None) -> np.ndarray:
        """(N,) copies whose last step failed (``failed`` ids), warned, or left a non-finite
        state or a velocity above `MAX_SPEED`."""
        unstable = ~np.logical_and.reduce(np.isfinite(self._qpos_qvel), axis=1)
        unstable |= np.add.reduce(self._warning_counts, axis=1) > warnings_before
        unstable |= np.maximum.reduce(np.abs(self.qvel), axis=1) > MAX_SPEED
        if failed is not None:
            unstable[failed] = True
        return unstable

    def _fallen(self) -> np.ndarray:
        height = self.head_pos[:, 2] - self.task.arena.fall_ground(self.head_pos[:, :2])
        return height < self.fall_height

    def _off_arena(self) -> np.ndarray:
        return np.logical_or.reduce(np.abs(self.head_pos[:, :2]) > self.arena_inside, axis=1)

    def _proprioception(self, ids: np.ndarray) -> np.ndarray:
        """Joint positions, body velocities and sensors of copies ``ids``."""
        state, sensors = self._qpos_qvel, self.sensordata
        if ids is not self.all:  # the common case needs no row selection
            state, sensors = state[ids], sensors[ids]
        return np.concatenate(
            [state[:, self._state_obs], sensors[:, self.sensor_index]], axis=1, dtype=np.float32
        )

    def _observe(self, ids: np.ndarray) -> Arrays:
        """Observations of copies ``ids``."""
        return {"proprioception": self._proprioception(ids), **self.task.observe(self, ids)}
