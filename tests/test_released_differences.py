"""Points where derl follows the released code (agrimgupta92/derl) against an earlier reading of
it (docs/fidelity.md): the box's friction, the stand height a `delete_limb` child keeps, the
ground the fall test reads, and the escape task's score (tests/test_eval_tasks.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.envs.terrain import TerrainConfig
from derl.evolution import Evolution, breed, load_profile
from derl.unimal import (
    Genome,
    Joint,
    Limb,
    body_hash,
    canonical_form,
    canonical_genome,
    mutate,
    sample_population,
)
from derl.unimal.geometry import layout
from derl.unimal.mjcf import FRICTION, rest_height

X = (Joint(axis="x", range=(-30, 30), gear=150),)


def test_the_box_has_the_released_default_geom_friction(quadruped: Genome) -> None:
    """The released box geom sets no friction: it takes unimal.xml's default geom class,
    ``friction="0.7 0.1 0.1"`` (MuJoCo's own default is 1); the ball sets its own."""
    for task, options in (
        ("mvt", {"terrain": TerrainConfig.manipulation(size_x=40.0, size_y=30.0)}),
        ("push_box_incline", {}),
    ):
        env = UnimalEnv(quadruped, make_task(task, **options), EnvConfig(num_envs=1))
        np.testing.assert_array_equal(env.model.geom("box").friction, FRICTION)
    ball = UnimalEnv(quadruped, make_task("manipulate_ball"), EnvConfig(num_envs=1))
    np.testing.assert_array_equal(ball.model.geom("box").friction, [0.7, 0.005, 0.005])


@pytest.fixture
def stilted() -> Genome:
    """A pair of legs and a forward limb, each 45 degrees down from the head, and a long leg
    straight down from the forward limb's end: the body stands on the long leg, 0.8 m high;
    without it, on the pair and the forward limb, 0.28 m."""
    return Genome(
        head_density=700,
        limb_density=600,
        limbs=(
            Limb(id=0, paired=True, length=0.2, theta=90, phi=135, joints=X),
            Limb(id=1, length=0.2, theta=0, phi=135, joints=X),
            Limb(id=2, parent=1, site="end", length=0.4, theta=0, phi=180, joints=X),
        ),
    )


def _without_the_long_leg(parent: Genome, released_delete: bool) -> Genome:
    """The first `delete_limb` child (seeds 0, 1, ...) that lost the long leg."""
    for seed in range(50):
        child, _ = mutate(
            parent, np.random.default_rng(seed), "delete_limb", released_delete=released_delete
        )
        if 2 not in child.by_id:
            return child
    raise AssertionError("no seed deleted the long leg")


def test_a_delete_limb_child_keeps_its_parents_stand_height(stilted: Genome) -> None:
    """The released `mutate_delete_limb` never calls `set_head_pos`: the child spawns at its
    parent's height and falls below half of it (here: at rest, on its remaining limbs)."""
    parent_height = rest_height(layout(stilted))
    assert parent_height == pytest.approx(0.35 * np.sqrt(0.5) + 0.55)  # the long leg's tip
    child = _without_the_long_leg(stilted, released_delete=True)
    own = rest_height(layout(child))
    assert own == pytest.approx(0.4 * np.sqrt(0.5))  # the other tips
    assert child.stand_height == pytest.approx(parent_height, abs=1e-6)
    # the switch off: the same child stands at its own height
    corrected = _without_the_long_leg(stilted, released_delete=False)
    assert corrected.stand_height is None
    assert corrected.limbs == child.limbs
    for genome, height in ((child, parent_height), (corrected, own)):
        env = UnimalEnv(genome, make_task("ft", size=20.0), EnvConfig(num_envs=2))
        env.reset(0)
        np.testing.assert_allclose(env.head_pos[:, 2], height + 0.2, atol=0.006)
        assert env.fall_height == pytest.approx(0.5 * height, abs=1e-6)
        env.qpos[:, env.root + 2] = own  # standing on its other limbs
        env.batch.forward()
        assert env._fallen().all() == (genome is child)


def test_the_operators_keep_or_reset_the_stand_height_as_the_released_code(
    stilted: Genome,
) -> None:
    """`grow_limb` and `limb_params` call `set_head_pos` in the released code; `density`,
    `dof`, `joint_angle` and `gear` do not (the child keeps its parent's MJCF head height), nor
    does `delete_limb` (the parent's height, kept again by a second deletion)."""
    parent = stilted.model_copy(update={"stand_height": 0.75})
    rng = np.random.default_rng(3)
    for op in ("density", "dof", "joint_angle", "gear"):
        assert mutate(parent, rng, op)[0].stand_height == 0.75
        assert mutate(parent, rng, op, released_delete=False)[0].stand_height is None
    for op in ("grow_limb", "limb_params"):
        assert mutate(parent, rng, op)[0].stand_height is None
    assert mutate(parent, rng, "delete_limb")[0].stand_height == 0.75
    assert mutate(stilted, rng, "density")[0].stand_height is None


def test_the_stand_height_is_part_of_the_body(stilted: Genome) -> None:
    """It changes the spawn and the fall test, so it is in the canonical form and the hash; a
    genome without it (an old one) loads, and its form and hash are unchanged."""
    kept = stilted.model_copy(update={"stand_height": 0.6})
    assert canonical_form(kept) == (*canonical_form(stilted), 0.6)
    assert body_hash(kept) != body_hash(stilted)
    assert canonical_genome(kept).stand_height == 0.6
    assert canonical_genome(stilted).stand_height is None
    old = stilted.model_dump_json(exclude={"stand_height"})
    assert "stand_height" not in old
    assert Genome.model_validate_json(old) == stilted
    assert Genome.model_validate_json(kept.model_dump_json()) == kept
    with pytest.raises(ValueError, match="greater than 0"):
        stilted.model_validate({**stilted.model_dump(), "stand_height": 0.0})


def test_the_fall_test_reads_the_ground_at_the_floored_cell(quadruped: Genome) -> None:
    """On rubble (up to 0.25 m between neighbouring vertices) the released code reads the ground
    under the head at the cell's corner, its position floored (`Terrain.pos_to_idx`), not at
    the nearest vertex: a head the nearest vertex puts below the fall height has not fallen."""
    terrain = TerrainConfig.variable(size_x=40.0, size_y=10.0, obstacles=("rubble",))
    env = UnimalEnv(quadruped, make_task("vt", terrain=terrain), EnvConfig(num_envs=2))
    env.reset(0)
    layout_ = env.task.arena.terrains.layout
    res = layout_.resolution
    for i, heights in enumerate(env.task.arena.terrains.heights):
        step = heights[:, 1:] - heights[:, :-1]  # vertex (r, c + 1) less vertex (r, c)
        rises = step > 0.1 if i == 0 else step < -0.1  # copy 0: uphill in +x; copy 1: downhill
        rows, cols = np.nonzero(rises)
        r, c = rows[len(rows) // 2], cols[len(cols) // 2]
        xy = np.array([layout_.x_min + (c + 0.7) * res, layout_.y_min + (r + 0.2) * res])
        floored, nearest = heights[r, c], heights[r, c + 1]
        # 5 mm above the fall height over the floored vertex (copy 0), 5 mm below it (copy 1):
        # over the nearest vertex, below it (copy 0) and above it (copy 1)
        margin = 0.005 if i == 0 else -0.005
        env.qpos[i, env.root : env.root + 3] = [*xy, floored + env.fall_height + margin]
        env.batch.forward()
        assert env._fallen()[i] == (i == 1)
        assert (nearest > floored + 0.1) if i == 0 else (nearest < floored - 0.1)
        assert env.task.arena.fall_ground(env.head_pos[:, :2])[i] == floored
        assert env.task.arena.ground(env.head_pos[:, :2])[i] == nearest
    # on a vertex, its own cell (floor(x * 10) as the released code: 0.3 / 0.1 < 3)
    cols, rows = np.meshgrid(np.arange(100, 300), np.arange(20, 80))
    xy = np.column_stack([(cols.ravel() - 200) / 10, (rows.ravel() - 50) / 10])
    ground = env.task.arena.terrains.ground(xy, np.zeros(len(xy), np.intp), floored=True)
    np.testing.assert_array_equal(ground, env.task.arena.terrains.heights[0][rows, cols].ravel())


def test_the_fall_test_on_a_slope_reads_the_released_staircase(quadruped: Genome) -> None:
    """On the slopes the released heights are whole 0.1 m treads, each at the slope's height at
    its lower end, 1/cos(10 deg) - 1 below the plane (its tilted floor box is 1 m thick)."""
    floor = make_task("incline", length=30.0, width=10.0).arena
    xy = np.array([[0.06, 0.0], [-0.04, 2.0], [3.0, 0.0]])
    expected = np.array([0.0, -0.1, 3.0]) * np.tan(np.deg2rad(10.0))
    expected -= 1 / np.cos(np.deg2rad(10.0)) - 1
    np.testing.assert_allclose(floor.fall_ground(xy), expected, atol=1e-12)
    np.testing.assert_allclose(floor.ground(xy), xy[:, 0] * np.tan(np.deg2rad(10.0)))


def test_the_profile_switch_gives_a_delete_limb_child_its_own_stand_height() -> None:
    """`released_delete_limb` (on by default, as the released code) reaches breeding: off, a
    child that lost a limb stands at its own resting height."""
    bodies = sample_population(6, np.random.default_rng(4))
    parents = [canonical_genome(g) for g in bodies if g.num_limbs >= 3]
    parent, seed = next(
        (parent, seed)
        for parent in parents
        for seed in range(200)
        if breed(parent, seed)[1].op == "delete_limb"
    )
    assert breed(parent, seed)[0].stand_height is not None
    corrected, mutation = breed(parent, seed, released_delete=False)
    assert mutation.op == "delete_limb" and corrected.stand_height is None
    for switch in (True, False):
        config = load_profile("smoke").model_copy(update={"released_delete_limb": switch})
        evolution = Evolution(config, [parent] * config.population)
        for k, child in enumerate(evolution.initial):
            evolution.birth(child.name, float(k), child.genome)
        evolution.record(replace(evolution.tournament(), mutation_seed=seed))
        body, _ = evolution.body("c00000")
        assert (body.stand_height is not None) is switch
