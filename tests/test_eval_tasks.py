"""The eight test tasks on small arenas: build, determinism, observation sizes, rewards on scripted
motions (bodies lifted and thrown in free flight), endings, and heightmaps against the heightfield.
The gymnasium checker runs over every registered task in test_envs.py."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from scipy import ndimage

from derl.envs import EnvConfig, StepResult, UnimalEnv, make_task
from derl.envs.arenas import Bowl, place_boxes
from derl.envs.eval_tasks import BowlConfig, ObstacleConfig, PushBoxPlacement
from derl.unimal import Genome

SMALL: dict[str, dict[str, object]] = {
    "patrol": {"size": 20.0},
    "point_nav": {"size": 40.0},
    "obstacle": {"config": ObstacleConfig(size_x=30.0, size_y=12.0, count=12, end_buffer=6.0)},
    "exploration": {"size": 20.0},
    "escape": {"config": BowlConfig(size=20.0)},
    "incline": {"length": 30.0, "width": 10.0},
    "push_box_incline": {
        "length": 30.0,
        "width": 10.0,
        "placement": PushBoxPlacement(box_x=-10.0, goal_x=10.0),
    },
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
    np.testing.assert_allclose(goal_point.goal[0], [5.0, 0.0, 0.1])  # 0.1 m above the floor
    np.testing.assert_allclose(env.head_pos[0, :2], [-5.0, 0.0], atol=0.01)  # at the other end
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
    seen = env.task.observe(env, env.all)["goal"][0]
    np.testing.assert_allclose(seen, [0, -5, -0.9], atol=1e-6)


def test_point_nav_pays_the_approach_and_the_bonus_at_the_goal(quadruped: Genome) -> None:
    """100 x the approach, +10 at every step within 0.5 m; arriving does not end the episode
    (the released code's ReachReward, and no success test)."""
    env = _env(quadruped, "point_nav")
    env.reset(3)
    task = env.task
    (goal,) = task.props
    assert task.success is None
    assert (np.abs(goal.goal[:, 0]) <= 20.0 - 6.5).all() and not np.array_equal(*goal.goal)
    assert (np.abs(goal.goal[:, 1]) <= 20.0 - 10.5).all()
    np.testing.assert_allclose(goal.goal[:, 2], 0.11)
    _fly(env, (5.0, 0.0, 0.0), xy=(0.0, 0.0))
    goal.goal[:, :2] = [[1.25, 0.0], [-8.0, 8.0]]
    task.placed(env, env.all)
    arrivals = 0
    for _ in range(20):
        before = env.head_pos[:, :2].copy()
        result = _idle(env)
        assert not result.terminated.any()
        after = env.head_pos[:, :2]
        d_before, d_after = (np.linalg.norm(goal.goal[:, :2] - p, axis=1) for p in (before, after))
        arrived = d_after <= 0.5
        arrivals += arrived[0]
        np.testing.assert_allclose(
            result.components["reach"], 100 * (d_before - d_after) + 10 * arrived, rtol=1e-9
        )
    assert arrivals == 10  # 1 m at 5 m/s: 10 steps within 0.5 m of the goal


GOAL_FLOOR_HALF = (100 / 2 - 6.5, 100 / 2 - 10.5)


def test_point_nav_goals_keep_the_released_codes_buffers() -> None:
    task = make_task("point_nav")
    (goal,) = task.props
    draws = goal.draw(np.random.default_rng(0), 4000)
    np.testing.assert_allclose(np.abs(draws).max(axis=0), GOAL_FLOOR_HALF, atol=0.1)
    assert (np.abs(draws) <= GOAL_FLOOR_HALF).all()
    with pytest.raises(ValueError, match="no room"):
        make_task("point_nav", size=20.0)


def test_exploration_pays_each_new_cell_once(quadruped: Genome) -> None:
    env = _env(quadruped, "exploration", n=1)
    env.reset(0)
    np.testing.assert_allclose(env.head_pos[0, :2], 0.0, atol=0.01)  # the centre: a cell corner
    visited: set[tuple[int, ...]] = set()  # the spawn cell is paid at the first step
    total = 0.0
    for velocity in (4.0, -6.0, 4.0):
        _fly(env, (velocity, 0.0, 0.0))
        for _ in range(20):
            result = _idle(env)
            cell = tuple(np.floor(env.head_pos[0, :2]).astype(int))
            assert result.components["explore"][0] == (cell not in visited)
            visited.add(cell)
            total += result.components["explore"][0]
    assert total == len(visited) >= 3


def test_incline_pays_the_distance_along_the_slope(quadruped: Genome) -> None:
    env = _env(quadruped, "incline")
    env.reset(0)
    x = env.head_pos[:, 0]
    spawn_height = env.rest_height + env.config.spawn_clearance
    np.testing.assert_allclose(env.head_pos[:, 2], x * np.tan(SLOPE) + spawn_height, atol=0.02)
    # the body spawns turned with the slope, upright on it (the released code's head euler)
    normal = np.array([-np.sin(SLOPE), 0.0, np.cos(SLOPE)])
    np.testing.assert_allclose(env.head_rot[:, :, 2], np.tile(normal, (env.num_envs, 1)), atol=0.02)
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
    ground = env.task.arena.fall_ground(env.head_pos[:, :2])  # the released code's staircase
    # The slopes' fall height is 20% of the resting height (50% elsewhere); copy 1 is 2 m above
    # the slope but below z = 0 (fallen, were it flat).
    assert env.fall_height == pytest.approx(0.2 * env.rest_height)
    env.qpos[:, env.root + 2] = ground + np.array([0.19 * env.rest_height, 2.0])
    env.batch.forward()
    assert env._fallen().tolist() == [True, False]
    env.qpos[0, env.root + 2] = ground[0] + 0.21 * env.rest_height
    env.batch.forward()
    assert not env._fallen().any()


def test_escape_pays_the_radial_gain_and_the_rim_bonus(quadruped: Genome) -> None:
    """The score ("escape", the fitness component) is the radial gain alone, as the released
    ``__reward__forward``; the +100 at the rim is paid in the reward as "rim" (the released
    `TerminateOnEscape` adds it to the reward only)."""
    env = _env(quadruped, "escape", n=1)
    assert env.task.fitness_component == "escape"
    env.reset(0)
    rim = env.task.success.rim
    assert rim == pytest.approx(0.84 * 10.0)
    _fly(env, (5.0, 0.0, 0.0), xy=(6.5, 0.0))
    for _ in range(30):
        before = np.linalg.norm(env.head_pos[0, :2])
        result = _idle(env)
        escape, bonus = result.components["escape"][0], result.components["rim"][0]
        assert result.reward[0] == pytest.approx(escape + bonus + result.components["ctrl"][0])
        if result.terminated[0]:
            break
        assert escape == pytest.approx(np.linalg.norm(env.head_pos[0, :2]) - before, rel=1e-9)
        assert bonus == 0.0
    else:
        pytest.fail("the rim was never reached")
    assert bonus == 100.0
    assert escape == pytest.approx(5.0 * 0.02, rel=0.05) and before < rim <= before + escape


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
    terrains = env.task.arena.terrains
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
    heights = env.task.arena.terrains.heights
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
    obj.reached[:] = True  # push pays once the agent has reached the object
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
    np.testing.assert_allclose(box[:, 0], -10.0)
    lift = box[:, 2] - box[:, 0] * np.tan(SLOPE)
    np.testing.assert_allclose(lift, 0.2 / np.cos(SLOPE))  # resting on the slope
    np.testing.assert_allclose(obj.goal[:, :2], [[10.0, 0.0]] * 2)
    np.testing.assert_allclose(obj.goal[:, 2], obj.goal[:, 0] * np.tan(SLOPE) + 0.11)
    assert obj.margin == 0.5
    for _ in range(25):  # it stays put
        _idle(env)
    np.testing.assert_allclose(obj.position, box[:, :3], atol=0.02)


def test_push_box_incline_is_the_released_codes() -> None:
    """A 0.4 m cube of 2 kg at x = -35, its goal at x = +35, on 80 m x 40 m at 10 degrees."""
    task = make_task("push_box_incline")
    (obj,) = task.props
    assert obj.placement.box_size == 0.4 and obj.placement.box_mass == 2.0
    box, goal = obj.placement.draw(np.random.default_rng(0), 2, task.arena.half, task.spawn)
    np.testing.assert_array_equal(box, [[-35.0, 0.0]] * 2)
    np.testing.assert_array_equal(goal, [[35.0, 0.0]] * 2)
    assert task.spawn[0] == pytest.approx(-38.0 * np.cos(SLOPE))


def test_ball_is_a_rolling_sphere_placed_like_the_box(quadruped: Genome) -> None:
    """The released code's ball task is MVT's on a flat 30 m corridor: spawn 2 m from the back
    edge, the ball a whole 15-24 m ahead (capped 6.2 m before the far edge), within 4.8 m of the
    centre line; its goal beyond (capped 6.5 m before the far edge: nearly always), within
    4.5 m; reached at its centre, within 0.5 m."""
    env = _env(quadruped, "manipulate_ball", n=64)
    model = env.model
    ball = model.geom("box")
    assert ball.type[0] == mujoco.mjtGeom.mjGEOM_SPHERE and ball.size[0] == 0.2
    assert model.geom_condim[ball.id] == 6
    mass = model.body_mass[model.body("box").id]
    assert mass == pytest.approx(600 * 4 / 3 * np.pi * 0.2**3)
    env.reset(0)
    (ball,) = env.task.props
    assert env.task.spawn == (-13.0, 0.0)
    np.testing.assert_allclose(env.head_pos[:, 0], -13.0, atol=0.01)
    x, y = ball.position[:, 0], ball.position[:, 1]
    capped = np.isclose(x, 15.0 - 6.2)
    assert capped.any() and (~capped).any()
    ahead = x[~capped] + 13.0
    np.testing.assert_allclose(ahead, np.round(ahead))
    assert ((ahead >= 15) & (ahead <= 21)).all()
    assert (np.abs(y) <= 4.8).all() and np.abs(y).max() > 4.0
    np.testing.assert_allclose(ball.position[:, 2], 0.2)  # resting on the floor
    goal = ball.goal
    np.testing.assert_allclose(goal[:, 0], 15.0 - 6.5)
    assert (np.abs(goal[:, 1]) <= 4.5).all()
    np.testing.assert_allclose(goal[:, 2], 0.11)
    overlap = (np.abs(goal[:, 0] - x) < 0.7) & (np.abs(goal[:, 1] - y) < 0.7)
    assert not overlap.any()
    np.testing.assert_array_equal(ball.reach_points(), ball.position[:, None])
    assert ball.margin == 0.5


def test_obstacle_boxes_are_placed_as_the_released_code() -> None:
    """Half-extents from {0.5, ..., 3} m, centres clear of both ends by 10 m plus the half
    extent, inside the sides, footprints not overlapping; spawn 3 m from the back edge."""
    config = ObstacleConfig()
    task = make_task("obstacle")
    assert task.spawn == (-75.0 + 3.0, 0.0)
    centre, half = place_boxes(config, np.random.default_rng(0))
    assert len(centre) == 50
    assert set(half.ravel()) <= {0.5, 1.0, 1.5, 2.0, 2.5, 3.0} and len(set(half.ravel())) == 6
    assert (centre[:, 0] - half[:, 0] >= -75.0 + 10.0).all()
    assert (centre[:, 0] + half[:, 0] <= 75.0 - 10.0).all()
    assert (np.abs(centre[:, 1]) + half[:, 1] <= 30.0).all()
    gap = np.abs(centre[:, None] - centre[None]) - (half[:, None] + half[None])
    apart = (gap >= -1e-12).any(axis=2)
    np.fill_diagonal(apart, True)
    assert apart.all()
    crowded = ObstacleConfig(size_x=30.0, size_y=12.0, count=200, end_buffer=6.0)
    assert len(place_boxes(crowded, np.random.default_rng(0))[0]) < 200  # some left out


def test_bowl_is_the_released_codes_cubic_zoom() -> None:
    """The bowl profile times ``ndimage.zoom`` (cubic spline) of size / 2 bump factors a side,
    as the released code's Bowl module, to float32 rounding."""
    config = BowlConfig(size=20.0)
    bowl = Bowl(config)
    heights = bowl.draw(np.random.default_rng(5))
    bumps = np.random.default_rng(5).uniform(0.15, 1.0, (10, 10))
    n = config.terrain.grid_shape[0]
    unit = np.linspace(-1.0, 1.0, n)
    radius = np.clip(np.hypot(unit[:, None], unit[None, :]), 0.04, 1.0)
    zoomed = ndimage.zoom(bumps, n / 10)
    assert zoomed.max() > 1.1  # the spline overshoots the factors
    expected = zoomed * 1.3 * (0.5 - np.cos(2 * np.pi * radius) / 2)
    assert heights.shape == (n, n)
    np.testing.assert_allclose(heights, np.clip(expected, 0.0, None), atol=1e-5)
    assert config.terrain.max_height == pytest.approx(1.3 * 1.3)
