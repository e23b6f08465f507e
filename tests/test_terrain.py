"""Tests of the procedural terrain, its MuJoCo hfield form and the batched heightmap observation."""

import itertools

import mujoco
import numpy as np
import pytest
from pydantic import ValidationError

from derl.envs.heightmap import HeightmapGrid, HeightStack, rough_columns, sample
from derl.envs.terrain import Terrain, TerrainConfig, _rubble, _rubble_layout, generate_terrain

SEEDS = range(25)


@pytest.fixture(scope="module")
def worlds() -> list[Terrain]:
    """VT and MVT worlds (same obstacles, different sizes) over many seeds."""
    configs = (TerrainConfig.variable(), TerrainConfig.manipulation())
    return [generate_terrain(c, np.random.default_rng(seed)) for seed in SEEDS for c in configs]


def _columns(terrain: Terrain, x_start: float, x_end: float) -> np.ndarray:
    """Height columns of vertices with x in [x_start, x_end)."""
    x = terrain.x_min + np.arange(terrain.ncol) * terrain.resolution
    return terrain.heights[:, (x >= x_start - 1e-6) & (x < x_end - 1e-6)]


def test_segment_lengths_follow_the_paper(worlds: list[Terrain]) -> None:
    kinds = set()
    for terrain in worlds:
        segments = terrain.segments
        assert segments[0].x_start == pytest.approx(terrain.x_min)
        assert segments[-1].x_end == pytest.approx(-terrain.x_min)
        for before, after in itertools.pairwise(segments):
            assert after.x_start == pytest.approx(before.x_end)
        interior = segments[1:-1]
        assert [s.kind == "flat" for s in interior] == [i % 2 == 0 for i in range(len(interior))]
        for segment in interior:
            low, high = (1.0, 3.0) if segment.kind == "flat" else (4.0, 8.0)
            assert low - 1e-9 <= segment.length <= high + 1e-9
            kinds.add(segment.kind)
    assert kinds == {"flat", "hills", "steps", "rubble"}


def test_obstacle_heights_follow_the_paper(worlds: list[Terrain]) -> None:
    for terrain in worlds:
        for segment in terrain.segments:
            block = _columns(terrain, segment.x_start, segment.x_end)
            assert block.min() >= 0.0
            if segment.kind == "flat":
                assert not block.any()
            elif segment.kind == "hills":
                assert 0.6 <= segment.height <= 1.2
                assert np.ptp(block, axis=0).max() == 0.0  # constant across y
                assert block.max() == pytest.approx(segment.height, abs=1e-2)
            elif segment.kind == "steps":
                levels = np.unique(np.round(block[0] / 0.2, 4))
                np.testing.assert_array_equal(levels, [1, 2, 3, 4])
                assert block.max() == pytest.approx(0.8)
                _check_step_profile(block[0])
            else:
                assert 0.2 <= segment.height <= 0.3
                assert block.max() == pytest.approx(segment.height, abs=1e-6)
                assert np.ptp(block, axis=0).max() > 0.0  # bumps vary across y too


def _check_step_profile(profile: np.ndarray) -> None:
    """4 treads up then 4 down (0.2, 0.4, 0.6, 0.8, 0.8, 0.6, 0.4, 0.2), each 1/8 long."""
    change = np.flatnonzero(np.diff(profile)) + 1
    treads = np.diff(np.concatenate(([0], change, [profile.size])))
    assert treads.size == 7  # the two 0.8 treads merge
    np.testing.assert_allclose(
        treads / profile.size, [1, 1, 1, 2, 1, 1, 1] / np.float64(8), atol=0.03
    )
    tops = profile[np.concatenate(([0], change))]
    np.testing.assert_allclose(tops, [0.2, 0.4, 0.6, 0.8, 0.6, 0.4, 0.2], atol=1e-6)


def test_start_area_is_flat_and_spawn_is_in_it(worlds: list[Terrain]) -> None:
    for terrain in worlds:
        start = TerrainConfig().start_flat
        assert terrain.spawn == pytest.approx((terrain.x_min + start / 2, 0.0))
        assert not _columns(terrain, terrain.x_min, terrain.x_min + start + 1.0).any()


def test_generation_is_deterministic_per_seed() -> None:
    config = TerrainConfig.manipulation()
    first, again, other = (generate_terrain(config, np.random.default_rng(s)) for s in (7, 7, 8))
    np.testing.assert_array_equal(first.heights, again.heights)
    assert first.segments == again.segments
    assert not np.array_equal(first.heights, other.heights)


def test_world_presets() -> None:
    rng = np.random.default_rng(0)
    flat = generate_terrain(TerrainConfig.flat(), rng)
    assert (flat.size_x, flat.size_y, flat.heights.shape) == (150.0, 150.0, (1501, 1501))
    assert not flat.heights.any()
    assert [s.kind for s in flat.segments] == ["flat"]
    vt = generate_terrain(TerrainConfig.variable(), rng)
    assert (vt.size_x, vt.size_y, vt.heights.shape) == (100.0, 100.0, (1001, 1001))
    mvt = generate_terrain(TerrainConfig.manipulation(), rng)
    assert (mvt.size_x, mvt.size_y, mvt.heights.shape) == (60.0, 40.0, (401, 601))
    assert {s.kind for s in mvt.segments} > {"flat"}


def test_heights_fit_the_hfield_elevation_scale(worlds: list[Terrain]) -> None:
    for terrain in worlds[:6]:
        field = terrain.hfield()
        assert field.size == (terrain.size_x / 2, terrain.size_y / 2, 1.5, 0.1)
        assert (field.nrow, field.ncol) == terrain.heights.shape
        assert field.data.dtype == np.float32 and field.data.shape == (terrain.heights.size,)
        assert field.data.min() >= 0.0 and field.data.max() <= 1.0
        np.testing.assert_allclose(field.data * 1.5, terrain.heights.ravel(), atol=1e-6)


def test_config_rejects_unknown_keys_and_impossible_heights() -> None:
    with pytest.raises(ValidationError):
        TerrainConfig(sizex=10.0)
    with pytest.raises(ValidationError):
        TerrainConfig(max_height=1.0)  # hills reach 1.2 m
    with pytest.raises(ValidationError):
        TerrainConfig(flat_length=(3.0, 1.0))
    with pytest.raises(ValueError):
        Terrain(heights=np.full((3, 3), 2.0, dtype=np.float32))


# --- MuJoCo agreement ---------------------------------------------------------------------------


def _hfield_model(terrain: Terrain) -> tuple[mujoco.MjModel, mujoco.MjData]:
    field = terrain.hfield()
    xml = f"""
    <mujoco>
      <asset>
        <hfield name="terrain" nrow="{field.nrow}" ncol="{field.ncol}"
                size="{" ".join(map(str, field.size))}"/>
      </asset>
      <worldbody><geom type="hfield" hfield="terrain"/></worldbody>
    </mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    terrain.write_to(model)
    mujoco.mj_forward(model, data)
    return model, data


def _ray_heights(model: mujoco.MjModel, data: mujoco.MjData, points: np.ndarray) -> np.ndarray:
    geomid = np.zeros(1, dtype=np.int32)
    down = np.array([0.0, 0.0, -1.0])
    start = 10.0
    dist = [
        mujoco.mj_ray(model, data, np.array([x, y, start]), down, None, 1, -1, geomid)
        for x, y in points
    ]
    return start - np.asarray(dist)


def test_height_at_matches_mujoco_rays_also_after_in_place_rewrite() -> None:
    config = TerrainConfig(size_x=20.0, size_y=10.0, start_flat=4.0)
    rng = np.random.default_rng(3)
    first = generate_terrain(config, np.random.default_rng(0))
    model, data = _hfield_model(first)
    for terrain in (first, generate_terrain(config, np.random.default_rng(1))):
        terrain.write_to(model)  # no recompile
        assert terrain.heights.max() > 0.2
        points = rng.uniform((-9.9, -4.9), (9.9, 4.9), size=(400, 2))
        hits = _ray_heights(model, data, points)
        np.testing.assert_allclose(hits, terrain.height_at(points[:, 0], points[:, 1]), atol=2e-3)
    with pytest.raises(ValueError):
        generate_terrain(TerrainConfig(size_x=20.0, size_y=12.0, start_flat=4.0), rng).write_to(
            model
        )


def test_height_at_interpolates_on_mujoco_triangles() -> None:
    heights = np.zeros((3, 3), dtype=np.float32)
    heights[0, 1] = 1.0  # vertex at (x, y) = (0, -1) of a 2 x 2 m world
    terrain = Terrain(heights=heights, resolution=1.0)
    np.testing.assert_allclose(
        terrain.height_at(
            np.array([-0.5, -0.25, -0.75, 0.0, 5.0]), np.array([-0.5, -0.75, -0.25, -1, -1])
        ),
        [0.0, 0.5, 0.0, 1.0, 0.0],
    )


def test_rubble_equals_its_float64_formula() -> None:
    """The float32 computation of rubble against the formula in float64, rounded once."""
    config = TerrainConfig.variable()
    for seed in range(5):
        block = np.zeros((101, 57), np.float32)
        _rubble(block, config, np.random.default_rng(seed))
        clip, (ix, tx), (iy, ty) = _rubble_layout(block.shape, config, np.random.default_rng(seed))
        pyramids = config.rubble_peak * np.minimum(ty[:, None], tx[None, :])
        expected = np.minimum(pyramids, clip[iy[:, None], ix[None, :]]).astype(np.float32)
        np.testing.assert_array_equal(block, expected)
        assert len(np.unique(block)) > 10


# --- heightmap ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def step_world() -> Terrain:
    """A 20 x 10 m world with a single 0.5 m step at x >= 1 m."""
    terrain = Terrain(heights=np.zeros((101, 201), dtype=np.float32))
    x = terrain.x_min + np.arange(terrain.ncol) * terrain.resolution
    heights = np.where(x >= 1.0 - 1e-9, 0.5, 0.0)[None, :].repeat(terrain.nrow, axis=0)
    return Terrain(heights=heights.astype(np.float32))


def test_default_grid_reproduces_the_original_design() -> None:
    grid = HeightmapGrid()
    assert (grid.nx, grid.ny, grid.size) == (30, 47, 1410)
    np.testing.assert_allclose(
        grid.forward[[0, 1, 6, -3, -2, -1]], [-1.0, -0.6, 0.0, 2.8, 3.2, 4.0]
    )
    np.testing.assert_allclose(grid.left, -grid.left[::-1])
    assert grid.offsets.shape == (1410, 2)
    gaps = np.diff(grid.forward[grid.forward >= 0])
    assert gaps[0] == pytest.approx(0.1) and gaps[-1] == pytest.approx(0.8)
    with pytest.raises(ValidationError):
        HeightmapGrid(front=4.0)


def test_heightmap_sees_step_ahead_not_behind(step_world: Terrain) -> None:
    grid = HeightmapGrid()
    forward = grid.offsets[:, 0]
    obs = sample(step_world, [[0.0, 0.0]], [0.0], grid)[0]
    assert obs.shape == (1410,) and obs.dtype == np.float32
    np.testing.assert_array_equal(obs[forward > 1.0], 0.5)
    np.testing.assert_array_equal(obs[forward < 0.9], 0.0)


def test_heightmap_turns_with_yaw(step_world: Terrain) -> None:
    grid = HeightmapGrid()
    forward, left = grid.offsets.T
    behind = sample(step_world, [[0.0, 0.0]], [np.pi], grid)[0]
    np.testing.assert_array_equal(behind[forward <= -1.0 + 1e-9], 0.5)
    np.testing.assert_array_equal(behind[forward > -0.9], 0.0)
    facing_left = sample(step_world, [[0.0, 0.0]], [np.pi / 2], grid)[0]
    np.testing.assert_array_equal(facing_left[left < -1.0], 0.5)  # the step is on its right
    np.testing.assert_array_equal(facing_left[left > -0.9], 0.0)


def test_heightmap_is_relative_to_ground_under_body(step_world: Terrain) -> None:
    grid = HeightmapGrid()
    forward = grid.offsets[:, 0]
    on_top = sample(step_world, [[1.5, 0.0]], [0.0], grid)[0]
    np.testing.assert_array_equal(on_top[forward >= -0.4], 0.0)
    np.testing.assert_array_equal(on_top[forward <= -0.6], -0.5)


def test_heightmap_outside_world_reads_edge(step_world: Terrain) -> None:
    obs = sample(step_world, [[9.0, 0.0]], [0.0], HeightmapGrid())[0]
    assert not obs.any()  # beyond x = 10 the edge height 0.5 continues


def test_batched_heightmap_equals_single_calls() -> None:
    terrain = generate_terrain(
        TerrainConfig(size_x=20.0, size_y=10.0, start_flat=4.0), np.random.default_rng(5)
    )
    grid = HeightmapGrid()
    rng = np.random.default_rng(0)
    xy = rng.uniform((-10.0, -5.0), (10.0, 5.0), size=(16, 2))
    yaw = rng.uniform(-np.pi, np.pi, size=16)
    batch = sample(terrain, xy, yaw, grid)
    singles = np.concatenate(
        [sample(terrain, xy[i : i + 1], yaw[i : i + 1], grid) for i in range(16)]
    )
    np.testing.assert_array_equal(batch, singles)
    assert batch.any()
    np.testing.assert_array_equal(batch[:, grid.offsets.tolist().index([0.0, 0.0])], 0.0)


def test_heightmap_reads_within_one_cell_of_the_exact_nearest_vertex() -> None:
    """The yaw-binned table lookup against exact rotation and rounding over random heads and
    yaws, on terrains whose heights are their row (column) index: every point reads a vertex at
    most one cell from the exact nearest one along each axis, and only the yaw bins make it differ
    from an exact rotation about the head's nearest vertex."""
    grid, n = HeightmapGrid(), 301
    index = np.arange(n, dtype=np.float32)
    rows = Terrain(heights=np.repeat(index[:, None], n, axis=1), max_height=n)
    cols = Terrain(heights=rows.heights.T, max_height=n)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-9.0, 9.0, (200, 2))  # the grid stays inside the 30 x 30 m world
    yaw = rng.uniform(-np.pi, np.pi, 200)
    head = (xy - rows.x_min) / rows.resolution  # (column, row) in cells
    head_vertex = np.floor(head + 0.5)
    forward, left = grid.offsets.T / rows.resolution
    cos, sin = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    rotated = np.stack([cos * forward - sin * left, sin * forward + cos * left], axis=2)
    relative = np.stack([sample(cols, xy, yaw, grid), sample(rows, xy, yaw, grid)], axis=2)
    read = relative + head_vertex[:, None]
    exact = np.floor(head[:, None] + rotated + 0.5)
    assert np.abs(read - exact).max() <= 1
    assert (read == exact).all(axis=2).mean() > 0.5
    about_head_vertex = head_vertex[:, None] + np.floor(rotated + 0.5)
    assert (read == about_head_vertex).all(axis=2).mean() > 0.95


def test_rough_columns_match_a_direct_window_check() -> None:
    rng = np.random.default_rng(0)
    heights = np.zeros((6, 80), np.float32)
    heights[:, 20:30] = 0.5  # a level stretch at another height
    heights[:, 45] = 0.2  # one level column
    heights[3, 60] = 0.1  # a column that varies along y
    heights[:, 70:] = rng.uniform(0, 1, (6, 10)).astype(np.float32)
    for reach in (1, 3, 7):
        expected = [
            len(np.unique(heights[:, max(c - reach, 0) : c + reach + 1])) > 1 for c in range(80)
        ]
        np.testing.assert_array_equal(rough_columns(heights, reach), expected)


def test_heightmap_skips_exactly_the_heads_that_see_one_height() -> None:
    """Skipping heads above level stretches gives what reading every point gives."""
    config = TerrainConfig(size_x=30.0, size_y=10.0, start_flat=8.0)
    terrains = [generate_terrain(config, np.random.default_rng(seed)) for seed in range(4)]
    stack = HeightStack(terrains[0], 4, HeightmapGrid())
    for i, terrain in enumerate(terrains):
        stack.write(i, terrain.heights)
    rng = np.random.default_rng(1)
    for which in (None, rng.integers(0, 4, 64)):
        n = 4 if which is None else 64
        xy = rng.uniform((-16.0, -6.0), (16.0, 6.0), (n, 2))
        yaw = rng.uniform(-np.pi, np.pi, n)
        heightmaps = stack.heightmap(xy, yaw, which)
        np.testing.assert_array_equal(heightmaps, stack.lookup(stack.vertices(xy, which), yaw))
    column = np.clip(np.rint((xy[:, 0] - terrains[0].x_min) / 0.1), 0, 300).astype(int)
    rough = stack.rough[which, column]
    assert rough.any() and not rough.all()
    assert heightmaps[rough].any() and not heightmaps[~rough].any()
