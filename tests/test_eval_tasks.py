"""The eight test tasks on small arenas: build, determinism, observation sizes, rewards on scripted
motions (bodies lifted and thrown in free flight), endings, and heightmaps against the heightfield.
The gymnasium checker runs over every registered task in test_envs.py."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from derl.envs import EnvConfig, StepResult, UnimalEnv, make_task
from derl.envs.eval_tasks import BowlConfig, ObstacleConfig
from derl.unimal import Genome

SMALL: dict[str, dict[str, object]] = {
    "patrol": {"size": 20.0},
    "point_nav": {"size": 20.0},
    "obstacle": {"config": ObstacleConfig(size_x=30.0, size_y=12.0, count=12, start_flat=6.0)},
    "exploration": {"size": 20.0},
    "escape": {"config": BowlConfig(size=20.0)},
    "incline": {"length": 30.0, "width": 10.0},
    "push_box_incline": {"length": 30.0, "width": 10.0},
    "manipulate_ball": {},
}
SLOPE = np.deg2rad(10.0)


def _env(genome: Genome, task: str, n: int = 2) -> UnimalEnv:
    return UnimalEnv(genome, make_task(task, **SMALL[task]), EnvConfig(num_envs=n))


def _fly(
    env: UnimalEnv, velocity: tuple[float, float, float], xy: tuple[float, float] | None = None
) -> None:
    """Throw every body from 3 m above the ground at ``xy`` (default: where it is)."""
    if xy is not None:
        env.qpos[:, env.root : env.root + 2] = xy
    ground = env.task.arena.ground(env.head_pos[:, :2])
    env.qpos[:, env.root + 2] = ground + 3.0
    env.qvel[:, :] = 0.0
    env.qvel[:, env.root_dof : env.root_dof + 3] = velocity
    env.batch.forward()


def _idle(env: UnimalEnv) -> StepResult:
    return env.step(np.zeros((env.num_envs, env.action_dim), np.float32))


@pytest.mark.parametrize("task", sorted(SMALL))
def test_builds_resets_deterministically_and_steps(quadruped: Genome, task: str) -> None:
    env = _env(quadruped, task)
    first, second = env.reset(7), env.reset(7)
    assert first.keys() == second.keys() == env.obs_spaces.keys()
    for key, size in env.obs_spaces.items():
        np.testing.assert_array_equal(first[key], second[key])
        assert first[key].shape == (env.num_envs, size) and first[key].dtype == np.float32
    rng = np.random.default_rng(0)
    for _ in range(20):
        result = env.step(rng.uniform(-1, 1, (env.num_envs, env.action_dim)).astype(np.float32))
        for key, size in env.obs_spaces.items():
            assert result.obs[key].shape == (env.num_envs, size)
            assert np.isfinite(result.obs[key]).all()
        assert np.isfinite(result.reward).all()
        assert env.task.fitness_component in result.components
    assert env.unstable_count == 0


def test_patrol_pays_the_approach_and_flips_the_goal(quadruped: Genome) -> None:
    env = _env(quadruped, "patrol", n=1)
    env.reset(0)
    task = env.task
    (goal_point,) = task.props
    np.testing.assert_allclose(goal_point.goal[0], [5.0, 0.0, 0.0])
    _fly(env, (4.0, 0.0, 0.0), xy=(3.8, 0.0))
    task.placed(env, env.all)
    goal, arrivals = 5.0, 0
    for _ in range(15):
        before = env.head_pos[0, :2].copy()
        reach = _idle(env).components["reach"][0]
        after = env.head_pos[0, :2]
        d_before, d_after = (np.hypot(goal - p[0], p[1]) for p in (before, after))
        arrived = d_after <= 0.5
        assert reach == pytest.approx(100 * (d_before - d_after) + 10 * arrived, rel=1e-9)
        if arrived:
            goal, arrivals = -goal, arrivals + 1
        assert goal_point.goal[0, 0] == goal
    assert arrivals == 1 and goal == -5.0


def test_goal_is_seen_in_the_head_frame(quadruped: Genome) -> None:
    env = _env(quadruped, "patrol", n=1)
    env.reset(0)
    yaw = np.pi / 2
    env.qpos[0, env.root : env.root + 7] = [0.0, 0.0, 1.0, np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]
    env.batch.forward()
    np.testing.assert_allclose(env.task.observe(env, env.all)["goal"][0], [0, -5, -1], atol=1e-9)


def test_point_nav_pays_the_approach_and_ends_on_arrival(quadruped: Genome) -> None:
    env = _env(quadruped, "point_nav")
    env.reset(3)
    task = env.task
    (goal,) = task.props
    assert (np.abs(goal.goal[:, :2]) <= 8.0).all() and not np.array_equal(*goal.goal)
    _fly(env, (5.0, 0.0, 0.0), xy=(0.0, 0.0))
    goal.goal[:] = [[1.25, 0.0, 0.0], [-8.0, 8.0, 0.0]]
    task.placed(env, env.all)
    for _ in range(20):
        before = env.head_pos[:, :2].copy()
        result = _idle(env)
        reach = result.components["reach"]
        assert not result.terminated[1]
        if result.terminated[0]:
            break
        after = env.head_pos[:, :2]
        d_before, d_after = (np.linalg.norm(goal.goal[:, :2] - p, axis=1) for p in (before, after))
        np.testing.assert_allclose(reach, 100 * (d_before - d_after), rtol=1e-9)
    else:
        pytest.fail("the goal was never reached")
    d_before = np.hypot(1.25 - before[0, 0], before[0, 1])
    assert 0.5 < d_before <= 0.6  # it arrived (within 0.5 m) on this step, moving 0.1 m
    assert reach[0] == pytest.approx(10 + 100 * 5.0 * 0.02, rel=0.05)


def test_exploration_pays_each_new_cell_once(quadruped: Genome) -> None:
    env = _env(quadruped, "exploration", n=1)
    env.reset(0)
    visited = {(0, 0)}  # the spawn cell, relative to the centre: not paid
    total = 0.0
    for velocity in (4.0, -6.0, 4.0):
        _fly(env, (velocity, 0.0, 0.0))
        for _ in range(20):
            result = _idle(env)
            cell = tuple(np.floor(env.head_pos[0, :2]).astype(int))
            assert result.components["explore"][0] == (cell not in visited)
            visited.add(cell)
            total += result.components["explore"][0]
    assert total == len(visited) - 1 >= 3


def test_incline_pays_the_distance_along_the_slope(quadruped: Genome) -> None:
    env = _env(quadruped, "incline")
    env.reset(0)
    x = env.head_pos[:, 0]
    spawn_height = env.rest_height + env.config.spawn_clearance
    np.testing.assert_allclose(env.head_pos[:, 2], x * np.tan(SLOPE) + spawn_height, atol=0.02)
    _fly(env, (1.5, 0.0, 0.0))
    x0 = env.head_pos[:, 0].copy()
    total = np.zeros(env.num_envs)
    for _ in range(20):
        result = _idle(env)
        assert not result.terminated.any()
        total += result.components["forward"]
    np.testing.assert_allclose(total, 50 * (env.head_pos[:, 0] - x0) / np.cos(SLOPE), rtol=1e-9)


def test_incline_ground_follows_the_slope(quadruped: Genome) -> None:
    env = _env(quadruped, "incline")
    env.reset(0)
    data = mujoco.MjData(env.model)
    mujoco.mj_forward(env.model, data)
    for x in (-10.0, 0.0, 12.0):
        hit = mujoco.mj_ray(env.model, data, [x, 4.0, 10.0], [0, 0, -1], None, 1, -1, None)
        ground = env.task.arena.ground(np.array([[x, 4.0]]))[0]
        assert 10.0 - hit == pytest.approx(ground, abs=1e-9)
        assert ground == pytest.approx(x * np.tan(SLOPE))
    ground = env.task.arena.ground(env.head_pos[:, :2])
    # Copy 0 lies on the slope; copy 1 is 2 m above it but below z = 0 (fallen, were it flat).
    env.qpos[:, env.root + 2] = ground + np.array([0.15 * env.rest_height, 2.0])
    env.batch.forward()
    assert _idle(env).terminated.tolist() == [True, False]


def test_escape_pays_the_radial_gain_and_the_rim_bonus(quadruped: Genome) -> None:
    env = _env(quadruped, "escape", n=1)
    env.reset(0)
    rim = env.task.success.rim
    assert rim == pytest.approx(0.84 * 10.0)
    _fly(env, (5.0, 0.0, 0.0), xy=(6.5, 0.0))
    for _ in range(30):
        before = np.linalg.norm(env.head_pos[0, :2])
        result = _idle(env)
        escape = result.components["escape"][0]
        if result.terminated[0]:
            break
        assert escape == pytest.approx(np.linalg.norm(env.head_pos[0, :2]) - before, rel=1e-9)
    else:
        pytest.fail("the rim was never reached")
    gain = escape - 100.0
    assert gain == pytest.approx(5.0 * 0.02, rel=0.05) and before < rim <= before + gain


def _ray_heights(model: mujoco.MjModel, xy: np.ndarray) -> np.ndarray:
    """Heightfield surface under each point, by ray casting onto the hfield geom alone."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    geom, top = model.geom("terrain").id, 10.0
    down = np.array([0.0, 0.0, -1.0])
    return np.array(
        [top - mujoco.mj_rayHfield(model, data, geom, [x, y, top], down) for x, y in xy]
    )


@pytest.mark.parametrize("task", ["obstacle", "escape"])
def test_heightmap_reads_the_heightfield(quadruped: Genome, task: str) -> None:
    env = _env(quadruped, task)
    env.reset(1)
    terrains = env.task.terrains
    layout = terrains.layout
    for i in range(env.num_envs):
        raised = terrains.heights[i] > 0.3
        raised[:45] = raised[-45:] = raised[:, :25] = raised[:, -45:] = False  # window on the grid
        rows, cols = np.nonzero(raised)
        r, c = rows[len(rows) // 2], cols[len(cols) // 2] - 15  # 1.5 m before a raised vertex
        head = [layout.x_min + c * layout.resolution, layout.y_min + r * layout.resolution]
        env.qpos[i, env.root : env.root + 7] = [*head, 3.0, 1.0, 0.0, 0.0, 0.0]
    env.batch.forward()
    heightmap = env.task.observe(env, env.all)["heightmap"]
    points = env.head_pos[:, None, :2] + env.task.arena.grid.offsets[None]
    for i, model in enumerate(terrains.models):
        surface = _ray_heights(model, np.vstack([env.head_pos[i, :2], points[i]]))
        np.testing.assert_allclose(heightmap[i], surface[1:] - surface[0], atol=1e-5)
        assert np.ptp(heightmap[i]) > 0.1


def test_obstacles_are_boxes_beyond_the_start_area(quadruped: Genome) -> None:
    env = _env(quadruped, "obstacle")
    env.reset(0)
    heights = env.task.terrains.heights
    assert set(np.unique(heights)) == {0.0, 2.0}
    assert not heights[:, :, : int(6.0 / 0.1)].any()  # the first 6 m are free
    assert 0.05 < (heights > 0).mean() < 0.9
    assert not np.array_equal(heights[0], heights[1])


@pytest.mark.parametrize("task", ["push_box_incline", "manipulate_ball"])
def test_push_reward_for_a_known_displacement(quadruped: Genome, task: str) -> None:
    env = _env(quadruped, task)
    env.reset(1)
    (obj,) = env.task.props
    box = env.free_joint("box_root")
    start = box.qpos[:, :2].copy()
    goal = start + np.array([4.0, 3.0])  # 5 m away
    obj.goal[:, :2] = goal
    box.qpos[:, 2] += 3.0  # the object flies toward the goal at 2 m/s
    box.qvel[:] = 0.0
    box.qvel[:, :2] = 2.0 * np.array([0.8, 0.6])
    env.batch.forward()
    env.task.placed(env, env.all)
    push = np.zeros(env.num_envs)
    for _ in range(10):
        push += _idle(env).components["push"]
    moved = 5.0 - np.linalg.norm(goal - box.qpos[:, :2], axis=1)
    np.testing.assert_allclose(push, 100 * moved, rtol=1e-6)
    np.testing.assert_allclose(moved, 2.0 * 10 * 0.02, rtol=0.02)


def test_box_lies_on_the_slope_below_the_goal(quadruped: Genome) -> None:
    env = _env(quadruped, "push_box_incline")
    env.reset(0)
    (obj,) = env.task.props
    box = env.free_joint("box_root").qpos.copy()
    np.testing.assert_allclose(box[:, 3:], [[np.cos(SLOPE / 2), 0, -np.sin(SLOPE / 2), 0]] * 2)
    np.testing.assert_allclose(box[:, 1], 0.0)
    np.testing.assert_allclose(box[:, 0], env.head_pos[:, 0] + 3.0, atol=0.01)
    lift = box[:, 2] - box[:, 0] * np.tan(SLOPE)
    np.testing.assert_allclose(lift, 0.2 / np.cos(SLOPE) + 0.01)
    np.testing.assert_allclose(obj.goal[:, :2], [[15.0 * np.cos(SLOPE) - 5.0, 0.0]] * 2)
    np.testing.assert_allclose(obj.goal[:, 2], obj.goal[:, 0] * np.tan(SLOPE))
    for _ in range(25):  # it stays put
        _idle(env)
    np.testing.assert_allclose(obj.position, box[:, :3], atol=0.02)


def test_ball_is_a_rolling_sphere_near_the_agent(quadruped: Genome) -> None:
    env = _env(quadruped, "manipulate_ball", n=16)
    model = env.model
    ball = model.geom("box")
    assert ball.type[0] == mujoco.mjtGeom.mjGEOM_SPHERE and ball.size[0] == 0.2
    assert model.geom_condim[ball.id] == 6
    mass = model.body_mass[model.body("box").id]
    assert mass == pytest.approx(600 * 4 / 3 * np.pi * 0.2**3)
    env.reset(0)
    (ball,) = env.task.props
    distance = np.linalg.norm(ball.position[:, :2], axis=1)
    assert ((distance >= 1.5) & (distance <= 4.0)).all()
    np.testing.assert_allclose(ball.position[:, 2], 0.21)
    goal = ball.goal[:, :2]
    assert (np.abs(goal) <= 12.0).all() and np.ptp(goal, axis=0).min() > 5
