"""Batched environments: rewards on scripted motions, endings, heightmap wiring, batch vs single,
and tasks as compositions of parts."""

from __future__ import annotations

import ast
from dataclasses import replace
from pathlib import Path

import gymnasium
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import derl.envs
from derl.envs import TASKS, EnvConfig, UnimalEnv, make_task
from derl.envs.arenas import Floor
from derl.envs.batched import MAX_SPEED
from derl.envs.endings import Escaped
from derl.envs.eval_tasks import ObstacleConfig
from derl.envs.flat_ground import AGENT_BIT, PLANE_NAME
from derl.envs.heightmap import sample
from derl.envs.rewards import REWARD_WEIGHTS, Forward, RewardWeights, RimBonus
from derl.envs.task import HOOKS, Part, RewardTerm, Task
from derl.envs.terrain import Terrain, TerrainConfig
from derl.envs.terrain_stack import HFIELD_NAME
from derl.envs.view import EnvView
from derl.unimal import Genome, Joint, Limb

SMALL_VT = TerrainConfig.variable(size_x=30.0, size_y=10.0)
SMALL_MVT = TerrainConfig.manipulation(size_x=40.0, size_y=24.0)
SMALL_OBSTACLE = ObstacleConfig(size_x=30.0, size_y=12.0, count=12, end_buffer=6.0)


def _env(genome: Genome, task: str, n: int = 4, **config: object) -> UnimalEnv:
    options = {"vt": {"terrain": SMALL_VT}, "mvt": {"terrain": SMALL_MVT}}.get(task, {})
    options = {"obstacle": {"config": SMALL_OBSTACLE}}.get(task, options)
    return UnimalEnv(genome, make_task(task, **options), EnvConfig(num_envs=n, **config))


def _lift(env: UnimalEnv, height: float, velocity: tuple[float, float, float]) -> None:
    """Put every head `height` above its spawn, moving at `velocity` (free flight)."""
    env.qpos[:, env.root + 2] += height
    env.qvel[:, :] = 0.0
    env.qvel[:, env.root_dof : env.root_dof + 3] = velocity
    env.batch.forward()


@pytest.mark.parametrize("task", ["ft", "vt"])
def test_forward_reward_is_fifty_times_the_distance(quadruped: Genome, task: str) -> None:
    env = _env(quadruped, task)
    env.reset(0)
    _lift(env, 5.0, (1.5, 0.0, 0.0))
    x0 = env.head_pos[:, 0].copy()
    total = np.zeros(env.num_envs)
    for _ in range(20):
        result = env.step(np.zeros((env.num_envs, env.action_dim), np.float32))
        assert not result.terminated.any()
        total += result.components["forward"]
        assert np.all(result.components["ctrl"] == 0)
    np.testing.assert_allclose(total, 50 * (env.head_pos[:, 0] - x0), rtol=1e-9)
    np.testing.assert_allclose(total, 50 * 1.5 * 20 * 0.02, rtol=0.02)


@pytest.mark.parametrize("frame_skip", [2, 8])
def test_forward_reward_is_metres_per_second_at_any_frame_skip(
    quadruped: Genome, frame_skip: int
) -> None:
    """The control step is the timestep x the frame skip, read by every part that needs it: the
    forward term stays the head's speed in m/s (an episode sum of distance / control step)."""
    env = _env(quadruped, "ft", frame_skip=frame_skip)
    assert env.control_dt == pytest.approx(0.005 * frame_skip)
    env.reset(0)
    _lift(env, 5.0, (1.5, 0.0, 0.0))
    x0 = env.head_pos[:, 0].copy()
    total = np.zeros(env.num_envs)
    for _ in range(10):
        total += env.step(np.zeros((env.num_envs, env.action_dim), np.float32)).components[
            "forward"
        ]
    distance = env.head_pos[:, 0] - x0
    np.testing.assert_allclose(total * env.control_dt, distance, rtol=1e-9)
    np.testing.assert_allclose(total / 10, 1.5, rtol=0.02)  # m/s: the launch speed


def test_fitness_bounds_come_from_the_terms_and_the_control_step() -> None:
    """A world's bound is its fitness terms' episode bounds: forward progress is at most the
    arena's diagonal per episode (so it scales with the weight and the control rate), MVT's
    reach and push the diagonal each plus their bonuses; a term that states no bound makes a
    fitness that sums it unbounded."""
    ft = make_task("ft")
    bound = EnvConfig().fitness_bound(ft)
    assert bound == pytest.approx(ft.arena.diagonal / 0.02)
    assert EnvConfig(frame_skip=8).fitness_bound(ft) == pytest.approx(bound / 2)
    heavy = make_task("ft", weights=RewardWeights(forward=3.0))
    assert EnvConfig().fitness_bound(heavy) == pytest.approx(3 * bound)
    mvt = make_task("mvt")
    w = REWARD_WEIGHTS["mvt"]
    expected = (w.reach + w.push) * mvt.arena.diagonal + w.bonus * (1 + 1000)
    assert EnvConfig().fitness_bound(mvt) == pytest.approx(expected)

    class Unbounded(RewardTerm):
        name = "mine"

    mine = Task("mine", "Mine", "mine", ft.arena, ft.spawn, (Unbounded(), *ft.rewards))
    assert EnvConfig().fitness_bound(mine) == float("inf")


def test_ctrl_cost_and_energy(quadruped: Genome) -> None:
    """The control cost is on the actions as the policy gave them, unclipped (the released
    code); MuJoCo gets them clipped to [-1, 1], and the energy (cost of work) is theirs."""
    env = _env(quadruped, "ft")
    env.reset(0)
    actions = np.full((env.num_envs, env.action_dim), 0.5, np.float32)
    actions[:, 0] = 3.0  # clipped to 1
    result = env.step(actions)
    expected = -1e-3 * (0.25 * (env.action_dim - 1) + 9.0)
    np.testing.assert_allclose(result.components["ctrl"], expected, rtol=1e-6)
    assert np.all(env.ctrl[:, 0] == 1.0)
    gears = env.model.actuator_gear[:, 0]
    np.testing.assert_allclose(result.components["energy"], 0.5 * gears.sum() + 0.5 * gears[0])


def test_push_and_reach_rewards(quadruped: Genome) -> None:
    """Push pays 100 x the box's approach to its goal once the agent has reached the box, and
    nothing before (the released code)."""
    env = _env(quadruped, "mvt", n=2)
    env.reset(1)
    task = env.task
    box = env.free_joint("box_root")
    (obj,) = task.props
    goal = obj.goal[:, :2].copy()
    start = box.qpos[:, :2].copy()
    toward = (goal - start) / np.linalg.norm(goal - start, axis=1, keepdims=True)
    box.qpos[:, 2] += 3.0  # the box flies toward the goal at 2 m/s
    box.qvel[:] = 0.0
    box.qvel[:, :2] = 2.0 * toward
    env.batch.forward()
    task.placed(env, np.arange(2))
    obj.reached[0] = True  # copy 0 has reached the box, copy 1 not
    push = np.zeros(2)
    for _ in range(10):
        result = env.step(np.zeros((2, env.action_dim), np.float32))
        push += result.components["push"]
    moved = np.linalg.norm(goal - start, axis=1) - np.linalg.norm(goal - box.qpos[:, :2], axis=1)
    np.testing.assert_allclose(push, [100 * moved[0], 0.0], rtol=1e-6)
    np.testing.assert_allclose(moved, 2.0 * 10 * 0.02, rtol=0.02)
    manipulation = result.components["manipulation"]
    np.testing.assert_allclose(manipulation, result.components["reach"] + result.components["push"])


def test_delivery_bonus_is_paid_at_every_step_at_the_goal(quadruped: Genome) -> None:
    env = _env(quadruped, "mvt", n=2)
    env.reset(1)
    task = env.task
    (obj,) = task.props
    box = env.free_joint("box_root")
    box.qpos[:, :2] = obj.goal[:, :2] + [[0.7, 0.0], [0.8, 0.0]]  # within 0.75 m, and not
    env.batch.forward()
    task.placed(env, env.all)
    obj.reached[:] = True
    for _ in range(3):
        push = env.step(np.zeros((2, env.action_dim), np.float32)).components["push"]
        assert push[0] == pytest.approx(10.0, abs=0.5) and abs(push[1]) < 0.5


def test_reach_bonus_is_paid_once(quadruped: Genome) -> None:
    env = _env(quadruped, "mvt", n=1)
    env.reset(2)
    head = env.head_pos[0].copy()
    env.free_joint("box_root").qpos[0, :3] = head + np.array([0.5, 0.0, 0.0])
    env.batch.forward()
    first = env.step(np.zeros((1, env.action_dim), np.float32)).components["reach"][0]
    second = env.step(np.zeros((1, env.action_dim), np.float32)).components["reach"][0]
    assert first > 9.0 and abs(second) < 5.0


def test_reward_terms_in_any_order_pay_the_same(quadruped: Genome) -> None:
    """Terms keep no state: they read the props', advanced before any term. MVT's terms listed
    in reverse pay what they pay in order, at the step the box is first reached too (push pays
    from that step on, its bonus included)."""
    runs = []
    for order in (1, -1):
        task = make_task("mvt", terrain=SMALL_MVT)
        task = replace(task, rewards=task.rewards[::order])
        env = UnimalEnv(quadruped, task, EnvConfig(num_envs=2))
        env.reset(1)
        (obj,) = env.task.props
        box = env.free_joint("box_root")
        head = env.head_pos[:, :2].copy()
        box.qpos[:, :2] = head + np.array([0.5, 0.0])  # within reach, sliding to the head
        box.qvel[:] = 0.0
        box.qvel[:, 0] = -1.0
        obj.goal[:, :2] = head - [[3.0, 0.0], [0.0, 0.0]]  # copy 1's within the margin
        env.batch.forward()
        env.task.placed(env, env.all)
        runs.append([env.step(np.zeros((2, env.action_dim), np.float32)) for _ in range(3)])
    first = runs[0][0].components
    assert (first["reach"] > 10.0).all() and first["push"][0] > 0.0 and first["push"][1] > 10.0
    for in_order, reversed_ in zip(*runs, strict=True):
        assert in_order.components.keys() == reversed_.components.keys()
        for key, values in in_order.components.items():
            np.testing.assert_array_equal(reversed_.components[key], values, err_msg=key)
        np.testing.assert_array_equal(reversed_.reward, in_order.reward)


def test_reward_terms_have_no_hooks() -> None:
    """No term keeps per-copy state: none sizes, resets or advances any (the props do)."""
    terms = [t for t in RewardTerm.__subclasses__() if t.__module__ == "derl.envs.rewards"]
    assert len(terms) >= 8
    for term in terms:
        assert [h for h in HOOKS if getattr(term, h) is not getattr(Part, h)] == [], term


def test_the_box_is_reached_at_its_face_centres(quadruped: Genome) -> None:
    """A 0.4 m cube (the released code's BOX_SIDE 0.2 is a half size), reached at the centres
    of its faces, which turn with it."""
    env = _env(quadruped, "mvt", n=1)
    assert env.model.geom("box").size.tolist() == [0.2, 0.2, 0.2]
    env.reset(2)
    (obj,) = env.task.props
    turn = np.pi / 4  # 45 degrees about z
    obj.qpos[0, :7] = [1.0, 2.0, 0.2, np.cos(turn / 2), 0.0, 0.0, np.sin(turn / 2)]
    env.batch.forward()
    points = obj.reach_points()[0]
    diagonal = 0.2 * np.sqrt(0.5)
    expected = [
        [1 + diagonal, 2 + diagonal, 0.2],
        [1 - diagonal, 2 - diagonal, 0.2],
        [1 - diagonal, 2 + diagonal, 0.2],
        [1 + diagonal, 2 - diagonal, 0.2],
        [1.0, 2.0, 0.4],
        [1.0, 2.0, 0.0],
    ]
    np.testing.assert_allclose(points, expected, atol=1e-12)
    agent = env.agent_points()[0]  # the head's bottom first (the released torso/btm_pos site)
    np.testing.assert_allclose(agent[0], env.head_pos[0] - 0.1 * env.head_rot[0, :, 2])
    nearest = np.linalg.norm(agent[:, None] - points[None], axis=2).min()
    assert obj.reach_distance(env)[0] == pytest.approx(nearest)


def test_object_is_seen_in_the_head_frame(quadruped: Genome) -> None:
    """All four parts of the "object" observation are rotated into the head frame, the angular
    velocity too (from the box's own frame, MuJoCo's qvel, through the world frame)."""
    env = _env(quadruped, "mvt", n=1)
    env.reset(2)
    (obj,) = env.task.props
    yaw = np.pi / 2  # head x axis along world +y
    head = env.qpos[0, env.root : env.root + 3].copy()
    env.qpos[0, env.root + 3 : env.root + 7] = [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
    env.qvel[0] = 0.0
    tilt = np.pi / 2  # the box turned 90 degrees about world x: its z axis is world -y
    obj.qpos[0, :3] = head + np.array([1.0, 2.0, 0.0])
    obj.qpos[0, 3:7] = [np.cos(tilt / 2), np.sin(tilt / 2), 0, 0]
    obj.velocity[0] = [0.5, 0.0, 0.0, 0.0, 0.0, 3.0]  # spinning about its own z: world -y
    env.batch.forward()
    seen = env.task.observe(env, env.all)["object"][0]
    goal = obj.goal[0] - env.head_pos[0]
    np.testing.assert_allclose(seen[0:3], [2.0, -1.0, 0.0], atol=1e-6)  # world (1, 2, 0)
    np.testing.assert_allclose(seen[3:6], [0.0, -0.5, 0.0], atol=1e-6)  # world (0.5, 0, 0)
    np.testing.assert_allclose(seen[6:9], [-3.0, 0.0, 0.0], atol=1e-6)  # world (0, -3, 0)
    np.testing.assert_allclose(seen[9:12], [goal[1], -goal[0], goal[2]], atol=1e-5)


def test_mvt_agents_see_the_box_and_goal_not_the_terrain() -> None:
    """The released code's MVT observes proprioception and the object only: its configuration
    lists the heightmap, but the manipulation environment never adds it."""
    assert make_task("mvt").obs_spaces() == {"object": 12}
    assert set(make_task("vt").obs_spaces()) == {"heightmap"}


def test_mvt_places_box_and_goal_as_the_released_code(quadruped: Genome) -> None:
    """The box a whole 15-24 m ahead of the spawn, the goal 15-24 m beyond it; 10 m (plus half
    sizes) kept free along the sides; the goal's centre 0.11 m above the ground."""
    task = make_task("mvt")
    env = UnimalEnv(quadruped, task, EnvConfig(num_envs=64))
    env.reset(0)
    (obj,) = task.props
    spawn_x = task.spawn[0]
    assert spawn_x == -27.0  # 3 m from the back edge of 60 m
    box, goal = obj.position, obj.goal
    ahead = box[:, 0] - spawn_x
    np.testing.assert_allclose(ahead, np.round(ahead))
    assert set(np.round(ahead).astype(int)) <= set(range(15, 25)) and len(set(ahead)) > 5
    beyond = goal[:, 0] - box[:, 0]  # never capped on 60 m: at most 3 + 48 m from the back
    np.testing.assert_allclose(beyond, np.round(beyond))
    assert (beyond >= 15).all() and (beyond <= 24).all()
    assert (np.abs(box[:, 1]) <= 20.0 - 10.0 - 0.2).all() and np.abs(box[:, 1]).max() > 7.0
    assert (np.abs(goal[:, 1]) <= 20.0 - 10.0 - 0.5).all()
    ground = task.arena.ground(goal[:, :2])
    np.testing.assert_allclose(goal[:, 2], ground + 0.11)


def test_fall_ends_the_episode(quadruped: Genome) -> None:
    env = _env(quadruped, "ft", n=2)
    env.reset(0)
    env.qpos[0, env.root + 2] = 0.3 * env.rest_height
    env.batch.forward()
    result = env.step(np.zeros((2, env.action_dim), np.float32))
    assert result.terminated.tolist() == [True, False]
    assert env.steps.tolist() == [0, 1]  # copy 0 was reset in place
    spawn_height = env.rest_height + env.config.spawn_clearance
    assert env.head_pos[0, 2] == pytest.approx(spawn_height, abs=0.02)


def test_a_body_spawns_and_falls_as_the_released_code() -> None:
    """`set_head_pos`: the head 0.2 m (FLOOR_OFFSET) above the body's lowest point, the lowest
    limb tip on its axis (a `btm_pos` site), not the rounded end below it; a fall is the head
    below half that resting height (`orig_height`)."""
    joint = Joint(axis="x", range=(-30, 60), gear=200)
    legs = Limb(id=0, paired=True, length=0.3, theta=45, phi=135, joints=(joint,))
    env = _env(Genome(head_density=700, limb_density=600, limbs=(legs,)), "ft", n=3)
    # tip: head radius 0.1, then 2 r + h = 0.4 along the leg, 45 degrees down
    assert env.rest_height == pytest.approx(0.5 * np.sqrt(0.5))
    assert env.config.spawn_clearance == 0.2
    env.reset(0)
    np.testing.assert_allclose(env.head_pos[:, 2], env.rest_height + 0.2, atol=0.006)
    assert env.fall_height == pytest.approx(0.5 * env.rest_height)


def test_time_limit_truncates(quadruped: Genome) -> None:
    env = _env(quadruped, "ft", n=2, episode_steps=5, fall_ratio=0.0)
    env.reset(0)
    for step in range(5):
        result = env.step(np.zeros((2, env.action_dim), np.float32))
        assert result.truncated.all() == (step == 4)
    assert not result.terminated.any()
    assert (result.final_obs["proprioception"] != result.obs["proprioception"]).any(axis=1).all()


def test_a_fall_at_the_time_limit_is_a_timeout(quadruped: Genome) -> None:
    """The released code marks a step at the limit a timeout even when it also ends the episode
    (`TimeLimitMask`: done at the limit), and its advantage then treats it as one."""
    env = _env(quadruped, "ft", n=2, episode_steps=1)
    env.reset(0)
    env.qpos[0, env.root + 2] = 0.3 * env.rest_height
    env.batch.forward()
    result = env.step(np.zeros((2, env.action_dim), np.float32))
    assert result.terminated.tolist() == [True, False]
    assert result.truncated.all()


def test_unstable_physics_ends_only_that_copy(quadruped: Genome) -> None:
    env = _env(quadruped, "ft", n=3)
    env.reset(0)
    env.qvel[1, 6:] = 1e12
    result = env.step(np.zeros((3, env.action_dim), np.float32))
    assert result.terminated.tolist() == [False, True, False]
    assert env.unstable_count == 1
    assert all(np.isfinite(v).all() for v in result.obs.values())
    assert result.components["forward"][1] == 0.0


def test_a_copy_flung_faster_than_any_body_moves_is_unstable(quadruped: Genome) -> None:
    """A finite blow-up that MuJoCo does not warn about (seen in a demo run: a body spun up in
    the air, then was flung 31 km in one step, a forward reward of 1.6 million)."""
    env = _env(quadruped, "ft", n=3)
    env.reset(0)
    env.qvel[1, 0] = 2 * MAX_SPEED  # the head at 200 m/s, forward
    result = env.step(np.zeros((3, env.action_dim), np.float32))
    assert result.terminated.tolist() == [False, True, False]
    assert env.unstable_count == 1
    assert result.components["forward"][1] == 0.0
    env.qvel[2, 0] = 0.5 * MAX_SPEED  # fast, but not absurd: the copy goes on
    assert not env.step(np.zeros((3, env.action_dim), np.float32)).terminated[2]


def test_batch_matches_single_simulations(quadruped: Genome) -> None:
    env = _env(quadruped, "ft", n=3, reset_noise=0.01, fall_ratio=0.0)
    env.reset(4)
    model = env.model
    singles = []
    for i in range(3):
        data = mujoco.MjData(model)
        data.qpos[:], data.qvel[:] = env.qpos[i], env.qvel[i]
        singles.append(data)
    rng = np.random.default_rng(0)
    for _ in range(50):
        actions = rng.uniform(-1, 1, (3, env.action_dim)).astype(np.float32)
        env.step(actions)
        for i, data in enumerate(singles):
            data.ctrl[:] = actions[i]
            mujoco.mj_step(model, data, nstep=4)
    for i, data in enumerate(singles):
        np.testing.assert_allclose(env.qpos[i], data.qpos, atol=1e-9)


def _fresh_observation(env: UnimalEnv, data: mujoco.MjData) -> np.ndarray:
    """Proprioception of a reset MjData placed at ``data.qpos``/``qvel``, as the released code's
    reset leaves it (`set_state`: mj_forward, every sensor)."""
    qpos, qvel = data.qpos.copy(), data.qvel.copy()
    mujoco.mj_resetData(env.model, data)
    data.qpos[:], data.qvel[:] = qpos, qvel
    mujoco.mj_forward(env.model, data)
    parts = (
        data.qpos[env.joint_qpos],
        data.qvel[env.agent_dofs],
        data.sensordata[env.sensor_index],
    )
    return np.concatenate(parts).astype(np.float32)


def test_reset_copy_matches_a_freshly_reset_simulation(quadruped: Genome) -> None:
    """A copy reset in `step` (its state rows rewritten) observes and moves as a reset MjData."""
    env = _env(quadruped, "ft", n=2)
    env.reset(0)
    rng = np.random.default_rng(0)
    for _ in range(10):
        env.step(rng.uniform(-0.3, 0.3, (2, env.action_dim)).astype(np.float32))
    env.qpos[0, env.root + 2] = 0.3 * env.rest_height
    env.batch.forward()
    result = env.step(np.zeros((2, env.action_dim), np.float32))
    assert result.terminated.tolist() == [True, False]
    data = mujoco.MjData(env.model)
    data.qpos[:], data.qvel[:] = env.qpos[0], env.qvel[0]
    fresh = _fresh_observation(env, data)
    np.testing.assert_array_equal(result.obs["proprioception"][0], fresh)
    assert (result.final_obs["proprioception"][0] != fresh).any()  # accelerations before reset
    running = (env.qpos[1, env.joint_qpos], env.qvel[1, env.agent_dofs], env.sensordata[1])
    expected = np.concatenate([*running[:2], running[2][env.sensor_index]]).astype(np.float32)
    np.testing.assert_array_equal(result.obs["proprioception"][1], expected)
    np.testing.assert_array_equal(env._qpos_qvel, np.hstack([env.qpos, env.qvel]))
    for _ in range(30):
        actions = rng.uniform(-0.3, 0.3, (2, env.action_dim)).astype(np.float32)
        assert not env.step(actions).terminated[0]
        data.ctrl[:] = actions[0]
        mujoco.mj_step(env.model, data, nstep=4)
    np.testing.assert_allclose(env.qpos[0], data.qpos, atol=1e-9)


def test_proprioception_is_the_released_codes(quadruped: Genome) -> None:
    """`Agent.observation_step`: joint angles, the body's velocities (free joint and joints),
    the head's accelerometer, gyro and velocimeter, every part's touch sensor, and each limb
    end's x and y in the head frame (`extremities`); at reset every sensor reads the spawn state
    (mj_forward): the accelerometer sees the joints' springs in free fall."""
    env = _env(quadruped, "ft", n=2)
    obs = env.reset(0)["proprioception"]
    joints, dofs, parts = len(env.joint_qpos), len(env.agent_dofs), 1 + 6  # head, six limbs
    assert obs.shape == (2, joints + dofs + 9 + parts + 2 * 6)
    head = env.model.body("head").id
    rot, centre = env.xmat[:, head].reshape(-1, 3, 3), env.head_pos
    sensors = [env.model.sensor(i).name for i in range(env.model.nsensor)]
    sites = [name.removesuffix("_pos") for name in sensors if name.endswith("_end_pos")]
    ends = env.site_xpos[:, [env.model.site(name).id for name in sites]]
    expected = np.einsum("nji,nkj->nki", rot, ends - centre[:, None])[:, :, :2]
    first_ends = joints + dofs + 9 + parts
    np.testing.assert_allclose(obs[:, first_ends:], expected.reshape(2, 12), rtol=1e-5, atol=1e-6)
    accelerometer = obs[:, joints + dofs : joints + dofs + 3]
    assert (np.abs(accelerometer) > 1e-3).all()


def test_heightmap_follows_the_heading(quadruped: Genome) -> None:
    env = _env(quadruped, "vt", n=2)
    env.reset(0)
    yaw = np.pi / 2
    env.qpos[1, env.root + 3 : env.root + 7] = [np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
    env.batch.forward()
    assert env.yaw[1] == pytest.approx(yaw)
    observed = env.task.observe(env, env.all)["heightmap"]
    for i in range(2):  # each copy reads its own terrain
        terrain = Terrain(
            env.task.arena.terrains.heights[i], SMALL_VT.resolution, SMALL_VT.max_height
        )
        expected = sample(terrain, env.head_pos[[i], :2], env.yaw[[i]], env.task.arena.grid)
        np.testing.assert_array_equal(observed[i], expected[0])


def test_new_terrain_for_every_episode(quadruped: Genome) -> None:
    """A copy that ends gets a fresh terrain, in its model (where the physics reads it) and in
    its heightmap; the others keep theirs."""
    env = _env(quadruped, "vt", n=3)
    env.reset(0)
    stack = env.task.arena.terrains
    before = stack.heights.copy()
    assert not np.array_equal(before[0], before[1])
    env.qpos[:2, env.root + 2] = 0.0  # copies 0 and 1 fall
    env.batch.forward()
    result = env.step(np.zeros((3, env.action_dim), np.float32))
    assert result.terminated[:2].all() and not result.terminated[2]
    after = stack.heights
    for i in range(2):
        assert not np.array_equal(before[i], after[i])
    np.testing.assert_array_equal(before[2], after[2])  # still running
    for i in range(3):  # the heightfield's data are heights / max_height
        model_heights = stack.models[i].hfield_data * SMALL_VT.max_height
        np.testing.assert_allclose(model_heights, stack.padded[i].ravel(), atol=1e-6)
    spawn_view = stack.heightmap(np.array([env.task.spawn] * 3), np.zeros(3))
    assert not spawn_view.any()  # from the spawn point no obstacle is in sight


def test_first_obstacles_are_uniform_over_the_episodes_started(quadruped: Genome) -> None:
    """The first obstacle lies 5, 7 or 9 m ahead of the spawn (a first flat of 2, 4 or 6 m),
    equally often over the episodes the copies start, even when episodes are short (early
    training): no terrain is kept for an episode that did not reach its obstacles, which
    favoured the farthest first obstacles (96% of the episodes in a rollout of random actions)."""
    corridor = TerrainConfig.variable(size_x=50.0, size_y=10.0)  # any first obstacle fits
    env = UnimalEnv(
        quadruped, make_task("vt", terrain=corridor), EnvConfig(num_envs=8, episode_steps=10)
    )
    env.reset(0)
    stack = env.task.arena.terrains
    starts = [stack.first_obstacle.copy()]
    rng = np.random.default_rng(0)
    for _ in range(250):
        result = env.step(rng.uniform(-1, 1, (env.num_envs, env.action_dim)).astype(np.float32))
        starts.append(stack.first_obstacle[result.terminated | result.truncated])
    ahead = np.concatenate(starts) - env.task.spawn[0]
    counts = np.array([np.count_nonzero(np.isclose(ahead, d)) for d in (5.0, 7.0, 9.0)])
    assert counts.sum() == len(ahead) > 200
    expected = len(ahead) / 3
    assert ((counts - expected) ** 2 / expected).sum() < 9.21  # chi-square, 2 dof, p = 0.01


def _ground_contacts(env: UnimalEnv, body: str | None = None) -> dict[str, np.ndarray]:
    """Per copy, how many contacts each ground (the flat stretches' plane, the heightfield)
    has, with the agent (``body`` None) or with the body ``body``."""
    model = env.model
    plane, heightfield = model.geom(PLANE_NAME).id, model.geom(HFIELD_NAME).id
    agent = model.geom_contype == AGENT_BIT
    counts = {"plane": np.zeros(env.num_envs, int), "heightfield": np.zeros(env.num_envs, int)}
    for i in range(env.num_envs):
        data = env.batch.get_data(i)
        for pair in data.contact.geom[: data.ncon]:
            other = pair[1] if pair[0] in (plane, heightfield) else pair[0]
            mine = agent[other] if body is None else model.geom_bodyid[other] == model.body(body).id
            for name, geom in (("plane", plane), ("heightfield", heightfield)):
                counts[name][i] += bool(mine and geom in pair)
    return counts


def test_flat_stretches_are_a_plane_and_obstacles_the_heightfield(quadruped: Genome) -> None:
    """As the released code's corridor (box geoms for the flat segments, heightfields for the
    obstacles): a body on a flat stretch touches a plane, which makes a capsule's 2 contacts
    where flat heightfield made up to 8, and a box's 4 where it made 49; carried onto its
    first obstacle, the body stands on the heightfield and not the plane below it."""
    env = _env(quadruped, "vt", fall_ratio=0.0)
    env.reset(0)
    zero = np.zeros((env.num_envs, env.action_dim), np.float32)
    touched = {"plane": 0, "heightfield": 0}
    for _ in range(40):
        env.step(zero)
        for name, count in _ground_contacts(env).items():
            touched[name] += count.sum()
    assert touched["plane"] > 40 and touched["heightfield"] == 0
    stack = env.task.arena.terrains
    on_hill = np.column_stack([stack.first_obstacle + 1.0, np.zeros(env.num_envs)])
    ground = env.task.arena.ground(on_hill)
    assert np.isfinite(on_hill).all() and (ground > 0.0).all()  # hills, steps and rubble rise
    env.qpos[:, env.root : env.root + 2] = on_hill
    env.qpos[:, env.root + 2] = ground + env.rest_height + 0.05
    env.qvel[:] = 0.0
    env.task.posed(env, env.all)  # the bodies moved: the grounds they touch follow
    env.batch.forward()
    touched = {"plane": 0, "heightfield": 0}
    for _ in range(40):
        result = env.step(zero)
        assert not result.terminated.any()
        for name, count in _ground_contacts(env).items():
            touched[name] += count.sum()
    assert touched["heightfield"] > 40 and touched["plane"] == 0
    assert (env.head_pos[:, 2] > env.task.arena.ground(env.head_pos[:, :2]) + 0.1).all()
    # MVT's box, simulated throughout: at rest on a flat stretch it touches the plane alone
    env = _env(quadruped, "mvt", n=16, sleep=False)
    env.reset(1)
    for _ in range(20):
        env.step(np.zeros((env.num_envs, env.action_dim), np.float32))
    box = _ground_contacts(env, "box")
    on_plane = box["plane"] > 0
    assert on_plane.any() and (box["plane"][on_plane] <= 4).all()
    assert not box["heightfield"][on_plane].any()
    # at rest on an obstacle: on the heightfield (with friction 0.7 a box may slide down one)
    still = ~on_plane & (np.abs(env.task.props[0].velocity).max(axis=1) < 0.01)
    assert still.any() and (box["heightfield"][still] > 4).all()


def test_terrain_is_written_ahead_of_the_body(quadruped: Genome) -> None:
    """A VT copy's terrain is written as its body comes near: after a reset, the start and the
    stretch ahead of it; a body carried along +x sees (heightmap, ground) what it would see were
    the whole terrain written at the reset."""
    corridor = TerrainConfig.variable(size_x=60.0, size_y=10.0)
    config = EnvConfig(num_envs=2, fall_ratio=0.0)
    env = UnimalEnv(quadruped, make_task("vt", terrain=corridor), config)
    env.reset(0)
    stack = env.task.arena.terrains
    rows, cols = stack.padded.shape[1:]
    area = stack.written[:, 0] * (stack.written[:, 2] - stack.written[:, 1])
    assert (area < rows * cols / 4).all()  # the start and what lies around it
    seen, heads, yaws, grounds = [], [], [], []
    for k in range(32):
        env.qpos[:, env.root] = env.task.spawn[0] + 1.5 * k
        env.qpos[:, env.root + 2] = 3.0
        env.batch.forward()
        result = env.step(np.zeros((2, env.action_dim), np.float32))
        seen.append(result.obs["heightmap"])
        heads.append(env.head_pos[:, :2].copy())
        yaws.append(env.yaw)
        grounds.append(env.task.arena.ground(env.head_pos[:, :2]))
    assert (stack.written[:, 0] > cols * 3 / 4).all()  # written as the bodies went
    for i, heights in enumerate(stack.heights):
        terrain = Terrain(heights, corridor.resolution, corridor.max_height)
        xy = np.array([head[i] for head in heads])
        yaw = np.array([y[i] for y in yaws])
        np.testing.assert_allclose(
            [obs[i] for obs in seen], sample(terrain, xy, yaw, env.task.arena.grid), atol=1e-5
        )
        vertex = np.rint((xy - [terrain.x_min, terrain.y_min]) / terrain.resolution).astype(int)
        np.testing.assert_allclose(
            [g[i] for g in grounds], heights[vertex[:, 1], vertex[:, 0]], atol=1e-6
        )


def test_reset_is_deterministic(quadruped: Genome) -> None:
    env = _env(quadruped, "mvt", n=2)
    first = env.reset(7)
    second = env.reset(7)
    for key in first:
        np.testing.assert_array_equal(first[key], second[key])


@pytest.mark.parametrize("task", sorted(TASKS))
def test_gymnasium_env_checker_passes(quadruped: Genome, task: str) -> None:
    env = gymnasium.make(f"derl/{make_task(task).gym_name}-v0", genome=quadruped)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


def test_changing_one_tasks_weights_leaves_the_others(
    quadruped: Genome, monkeypatch: pytest.MonkeyPatch
) -> None:
    """FT, VT and obstacle share the forward term, not its weights: VT's entry of the table is
    VT's alone."""
    monkeypatch.setitem(REWARD_WEIGHTS, "vt", RewardWeights(forward=2.0))
    for task, scale in (("ft", 1.0), ("vt", 2.0), ("obstacle", 1.0)):
        env = _env(quadruped, task)
        env.reset(0)
        _lift(env, 5.0, (1.5, 0.0, 0.0))
        x0 = env.head_pos[:, 0].copy()
        forward = env.step(np.zeros((env.num_envs, env.action_dim), np.float32)).components
        dx = env.head_pos[:, 0] - x0
        np.testing.assert_allclose(forward["forward"], scale * 50 * dx, rtol=1e-9)


def test_a_task_composed_from_parts(quadruped: Genome) -> None:
    """A new task is a list of parts: FT's floor, its forward term and escape's rim test."""
    weights = RewardWeights()
    task = Task(
        name="run_out",
        gym_name="RunOut",
        fitness_component="forward",
        arena=Floor(20.0, 20.0),
        spawn=(0.0, 0.0),
        rewards=(Forward(weights), RimBonus(3.0, RewardWeights(bonus=5.0))),
        success=Escaped(3.0),
    )
    env = UnimalEnv(quadruped, task, EnvConfig(num_envs=2))
    assert env.obs_spaces.keys() == {"proprioception"}
    env.reset(0)
    _lift(env, 3.0, (5.0, 0.0, 0.0))
    for _ in range(40):
        result = env.step(np.zeros((2, env.action_dim), np.float32))
        np.testing.assert_allclose(
            result.reward, result.components["forward"] + result.components["rim"]
        )
        if result.terminated.all():
            break
    else:
        pytest.fail("the rim was never reached")
    assert (result.components["rim"] == 5.0).all()


def test_a_task_checks_its_components() -> None:
    weights = RewardWeights()
    parts = {"arena": Floor(10.0, 10.0), "spawn": (0.0, 0.0), "rewards": (Forward(weights),)}
    with pytest.raises(ValueError, match="no component 'reach'"):
        Task(name="t", gym_name="T", fitness_component="reach", **parts)
    with pytest.raises(ValueError, match="metric total sums unknown terms"):
        Task(name="t", gym_name="T", fitness_component="total", metrics={"total": ("x",)}, **parts)
    with pytest.raises(ValueError, match="share a name"):
        Task(
            name="t",
            gym_name="T",
            fitness_component="forward",
            **parts | {"rewards": (Forward(weights), Forward(weights))},
        )


def test_parts_see_the_environment_through_its_view(quadruped: Genome) -> None:
    env = _env(quadruped, "mvt", n=2)
    assert isinstance(env, EnvView)
    with pytest.raises(ValueError, match="not a free joint"):
        env.free_joint(env.model.joint(1).name)
    with pytest.raises(ValueError, match="not a mocap body"):
        env.mocap_pos("box")
    env.reset(3)
    (box,) = env.task.props
    np.testing.assert_array_equal(env.mocap_pos("goal"), box.goal)


def test_task_modules_do_not_import_the_environment() -> None:
    """Parts and tasks know the environment only as an `EnvView` (no import cycle)."""
    package = Path(derl.envs.__file__).parent
    for module in (
        "task",
        "view",
        "rewards",
        "observations",
        "arenas",
        "objects",
        "endings",
        "worlds",
        "eval_tasks",
        "registry",
    ):
        tree = ast.parse((package / f"{module}.py").read_text())
        imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)} | {
            alias.name
            for node in ast.walk(tree)
            if isinstance(node, ast.Import)
            for alias in node.names
        }
        assert "derl.envs.batched" not in imported, module


def _box_run(genome: Genome, sleep: bool, nudge: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """MVT boxes of 16 copies whose bodies do nothing: untouched for 100 steps, pushed along +x
    by 30 N for 10 steps (``nudge``: moved that far along +x first), left for 90, then the
    bodies dropped onto them for 100; the boxes' positions (steps, copies, 3) and whether they
    were asleep after steps 100, 102, 110 and 202 (4, copies)."""
    task = make_task("mvt", terrain=SMALL_MVT)
    env = UnimalEnv(genome, task, EnvConfig(num_envs=16, sleep=sleep, fall_ratio=0.0))
    env.reset(3)
    (obj,) = task.props
    box = env.model.body("box").id
    push = env.batch.bind("xfrc_applied")[:, box, 0]
    zero = np.zeros((env.num_envs, env.action_dim), np.float32)
    positions, asleep = [], []
    for t in range(300):
        if t == 100:
            obj.qpos[:, 0] += nudge
            push[:] = 30.0
        if t == 110:
            push[:] = 0.0
        if t == 200:
            env.qpos[:, env.root : env.root + 2] = obj.position[:, :2]
            env.qpos[:, env.root + 2] = obj.position[:, 2] + 0.6
            env.qvel[:] = 0.0
            task.posed(env, env.all)  # the bodies moved: the grounds they touch follow
            env.batch.forward()
        result = env.step(zero)
        assert not (result.terminated | result.truncated).any()
        positions.append(obj.position.copy())
        if t in (99, 101, 109, 201):
            data = [env.batch.get_data(i) for i in range(env.num_envs)]
            asleep.append([d.tree_asleep[env.model.body_treeid[box]] >= 0 for d in data])
    return np.array(positions), np.array(asleep)


def test_sleeping_boxes_move_as_awake_ones(quadruped: Genome) -> None:
    """MuJoCo's sleeping freezes MVT's box once it rests (its contacts with the ground skipped:
    4 with a flat stretch's plane, about 40 with an obstacle's heightfield) until a push or a
    body wakes it. Untouched, a sleeping box stays within 0.5 mm of the box simulated
    throughout; pushed or hit, it moves as that box does, up to the spread that a 0.1 mm shift
    of the box gives (sliding over contacts that come and go magnifies any difference: 0.1 mm
    becomes tens of cm), and nothing stays asleep."""
    slept, asleep = _box_run(quadruped, sleep=True)
    awake, never = _box_run(quadruped, sleep=False)
    nudged, _ = _box_run(quadruped, sleep=False, nudge=1e-4)
    assert not never.any()
    assert asleep[0].mean() >= 0.5  # at rest, most boxes sleep...
    assert not asleep[1:].any()  # ...and wake when pushed or hit
    np.testing.assert_allclose(slept[:100], awake[:100], atol=5e-4)
    moved = np.linalg.norm(awake[199, :, :2] - awake[99, :, :2], axis=1)
    moved_slept = np.linalg.norm(slept[199, :, :2] - slept[99, :, :2], axis=1)
    assert moved.mean() > 1.0 and abs(moved_slept.mean() - moved.mean()) < 0.15 * moved.mean()
    for start, end in ((100, 200), (200, 300)):  # pushed, hit
        apart = np.abs(slept[start:end] - awake[start:end]).max(axis=(0, 2))
        spread = np.abs(nudged[start:end] - awake[start:end]).max(axis=(0, 2))
        assert np.median(apart) < 2 * np.median(spread)
