"""Tests of the procedural terrain, its MuJoCo hfield form and the batched heightmap observation."""

import itertools

import mujoco
import numpy as np
import pytest
from pydantic import ValidationError
from scipy.signal import sawtooth

from derl.envs.heightmap import HeightmapGrid, HeightStack, rough_columns, sample
from derl.envs.terrain import (
    Segment,
    Span,
    Terrain,
    TerrainConfig,
    _rubble,
    _rubble_strips,
    generate_terrain,
    plan_terrain,
    render,
)
from derl.envs.terrain_stack import TerrainStack, add_hfield

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


def _rubble_profile(n: int, half_periods: int, clip: float) -> np.ndarray:
    """The released code's rubble strip over n columns, with scipy's own triangle wave."""
    return np.clip(sawtooth(np.linspace(0, half_periods * np.pi, num=n), width=0.5) + 1, None, clip)


def test_segment_kinds_and_lengths_follow_the_released_code(worlds: list[Terrain]) -> None:
    lengths: dict[str, set[float]] = {
        "flat": set(),
        "hills": set(),
        "steps": set(),
        "rubble": set(),
    }
    flat_after_skip = 0
    for terrain in worlds:
        segments = terrain.segments
        assert segments[0] == Segment("flat", terrain.x_min, terrain.x_min + 6.0, 0.0)
        assert segments[-1].x_end == pytest.approx(-terrain.x_min)
        for before, after in itertools.pairwise(segments):
            assert after.x_start == pytest.approx(before.x_end)
            assert before.kind == "flat" or after.kind == "flat"  # every obstacle after a flat
            if before.kind == after.kind == "flat" and before is not segments[0]:
                # an obstacle was skipped: none fits in what is left after the first flat
                assert -terrain.x_min - before.x_end < 32.0
                flat_after_skip += 1
        *body, last = segments[1:]
        for segment in body:
            lengths[segment.kind].add(round(segment.length, 6))
        if last.kind == "flat":
            assert 0 < last.length <= 6.0 + 1e-9  # cut at the far end
        else:
            lengths[last.kind].add(round(last.length, 6))
    assert lengths == {
        "flat": {2.0, 4.0, 6.0},
        "hills": {8.0, 16.0},
        "steps": {24.0, 32.0},
        "rubble": {8.0, 16.0},
    }
    assert flat_after_skip > 0


def test_obstacle_heights_follow_the_released_code(worlds: list[Terrain]) -> None:
    hill_heights, rubble_rows = set(), set()
    profiles = {(f, c): None for f in (10, 15) for c in (0.2, 0.3)}  # (half-periods, clip)
    for terrain in worlds:
        for segment in terrain.segments:
            block = _columns(terrain, segment.x_start, segment.x_end)
            n = block.shape[1]
            assert block.min() >= 0.0
            if segment.kind == "flat":
                assert not block.any()
            elif segment.kind == "hills":
                hill_heights.add(round(segment.height, 6))
                expected = segment.height * np.sin(np.linspace(0, np.pi, num=n))
                np.testing.assert_allclose(block, np.broadcast_to(expected, block.shape), atol=1e-6)
            elif segment.kind == "steps":
                assert segment.height == pytest.approx(0.6)
                _check_step_profile(block)
            else:
                assert segment.height in (0.2, 0.3)
                assert block.max() == pytest.approx(segment.height, abs=1e-6)
                # every row is the released profile of one (half-periods, clip) pair
                candidates = np.array([_rubble_profile(n, f, c) for f, c in profiles])
                distance = np.abs(block[:, None, :] - candidates[None]).max(axis=2)
                assert distance.min(axis=1).max() < 1e-6
                rubble_rows.update(distance.argmin(axis=1).tolist())
    assert hill_heights == {0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2}
    assert rubble_rows == set(range(len(profiles)))


def _check_step_profile(block: np.ndarray) -> None:
    """8 treads of 1/8 of the length, constant across y, at 0, 0.2, 0.4, 0.6, 0.6, 0.4, 0.2, 0:
    the top one doubled."""
    np.testing.assert_array_equal(block, np.broadcast_to(block[0], block.shape))
    treads = block[0].reshape(8, -1)
    np.testing.assert_array_equal(treads, np.broadcast_to(treads[:, :1], treads.shape))
    levels = np.array([0, 0.2, 0.4, 0.6, 0.6, 0.4, 0.2, 0], np.float32)
    np.testing.assert_array_equal(treads[:, 0], levels)


@pytest.mark.parametrize("n", [80, 160])
def test_rubble_strips_are_clipped_triangle_waves(n: int) -> None:
    """Strips 1.0-1.9 m wide across the corridor, each a triangle wave along x with 10 or 15
    half-periods over the obstacle, clipped at 0.2 or 0.3 m."""
    config = TerrainConfig.variable()
    seen: set[tuple[int, int, float]] = set()
    for seed in range(8):
        block = np.zeros((1001, n), np.float32)
        span = Span("rubble", 0, n, *_rubble(n, 1001, config, np.random.default_rng(seed)))
        render([span], block, (0, 1001), (0, n))
        height = span.top
        rows, wave, clip = _rubble_strips(1001, config, np.random.default_rng(seed))
        assert set(rows.tolist()) <= set(range(10, 20))
        assert rows[:-1].sum() < 1001 <= rows.sum()  # the last strip is cut by the edge
        half_periods = np.array(config.rubble_half_periods)[wave]
        clips = np.array(config.rubble_clip)[clip]
        assert height == clips.max()
        starts = np.concatenate(([0], np.cumsum(rows)[:-1]))
        for start, width, f, c in zip(starts, rows, half_periods, clips, strict=True):
            strip = block[start : start + width]
            np.testing.assert_allclose(
                strip, np.broadcast_to(_rubble_profile(n, f, c), strip.shape), atol=1e-6
            )
            # the wave peaks once every two half-periods: 5 plateaus at the clip for 10, 8 for
            # 15 (the last one at the far end)
            at_clip = np.concatenate(([0], strip[0] == np.float32(c), [0])).astype(int)
            assert np.count_nonzero(np.diff(at_clip) == 1) == {10: 5, 15: 8}[f]
            seen.add((int(width), int(f), float(c)))
    assert {(f, c) for _, f, c in seen} == {(10, 0.2), (10, 0.3), (15, 0.2), (15, 0.3)}
    assert {w for w, _, _ in seen} == set(range(10, 20))


def test_start_flat_is_centred_on_the_spawn_point(worlds: list[Terrain]) -> None:
    """6 m of flat ground centred on the spawn point, then a flat of 2, 4 or 6 m: the first
    obstacle begins 5, 7 or 9 m ahead of the spawn point."""
    ahead = set()
    for terrain in worlds:
        spawn_x = terrain.spawn[0]
        assert terrain.spawn == (terrain.x_min + 3.0, 0.0)
        start = terrain.segments[0]
        assert (start.kind, start.x_start + start.x_end) == ("flat", pytest.approx(2 * spawn_x))
        assert start.length == pytest.approx(6.0)
        assert not _columns(terrain, terrain.x_min, terrain.first_obstacle).any()
        ahead.add(round(terrain.first_obstacle - spawn_x, 6))
    assert ahead == {5.0, 7.0, 9.0}


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
        TerrainConfig(flat_length=())
    with pytest.raises(ValidationError):
        TerrainConfig(flat_length=(2.0, -1.0))
    with pytest.raises(ValidationError):
        TerrainConfig(rubble_half_periods=(0, 10))
    with pytest.raises(ValidationError):
        TerrainConfig(steps_length=(24.0, 30.0))  # 300 cells are not 8 whole treads
    with pytest.raises(ValidationError):
        TerrainConfig(flat_length=(2.05,))  # not whole cells
    with pytest.raises(ValidationError):
        TerrainConfig(num_steps=6, step_height=0.8)  # steps reach 1.6 m
    TerrainConfig(max_height=1.2)  # the highest hill fits exactly
    with pytest.raises(ValueError):
        Terrain(heights=np.full((3, 3), 2.0, dtype=np.float32))


# --- MuJoCo agreement ---------------------------------------------------------------------------


def _ray_heights(model: mujoco.MjModel, points: np.ndarray) -> np.ndarray:
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    geomid = np.zeros(1, dtype=np.int32)
    down = np.array([0.0, 0.0, -1.0])
    start = 10.0
    dist = [
        mujoco.mj_ray(model, data, np.array([x, y, start]), down, None, 1, -1, geomid)
        for x, y in points
    ]
    return start - np.asarray(dist)


def test_terrains_drawn_in_place_are_what_mujoco_sees() -> None:
    """A terrain drawn straight into a model's padded heightfield (no recompile), again and
    again: MuJoCo's surface passes through the vertices of the ground the environment reads
    (`TerrainStack.ground`), the same draws as `generate_terrain`'s, and continues at its edge
    heights beyond the edges (between vertices MuJoCo interpolates on its own triangles)."""
    config = TerrainConfig(size_x=20.0, size_y=10.0, start_flat=4.0)
    spec = mujoco.MjSpec()
    add_hfield(spec, config, HeightmapGrid())
    model = spec.compile()
    stack = TerrainStack(config, model, 1, HeightmapGrid())
    rng = np.random.default_rng(3)
    for seed in (1, 2):  # rubble, hills
        stack.renew(np.array([0]), np.random.default_rng(seed))
        terrain = Terrain(stack.heights[0], config.resolution, config.max_height)
        drawn = generate_terrain(config, np.random.default_rng(seed))
        np.testing.assert_allclose(terrain.heights, drawn.heights, atol=1e-6)
        assert terrain.heights.max() > 0.2
        rough = rough_columns(terrain.heights, stack.margin)  # heads that need a lookup
        assert rough.any() and not (rough & ~stack.rough[0]).any()
        # vertices (column, row), up to 2 m beyond the edges too
        beyond = round(2.0 / config.resolution)
        cells = rng.integers(-beyond, np.array(config.grid_shape)[::-1] + beyond, size=(400, 2))
        points = np.array([stack.layout.x_min, stack.layout.y_min]) + cells * config.resolution
        # cast a hair inside a triangle: a ray at a vertex can slip between the triangles there
        hits = _ray_heights(stack.models[0], points + np.array([1e-5, 5e-6]))
        np.testing.assert_allclose(hits, stack.ground(points, np.zeros(400, int)), atol=2e-4)


def test_level_holds_over_flat_stretches_only() -> None:
    """`TerrainStack.level`, which gives a body the plane instead of the heightfield: true for
    every stretch of x inside a flat segment (the start included, and beyond the ends), false
    wherever a vertex under it, or next to it, is not at z = 0."""
    config = TerrainConfig(size_x=40.0, size_y=10.0, start_flat=4.0)
    spec = mujoco.MjSpec()
    add_hfield(spec, config, HeightmapGrid())
    stack = TerrainStack(config, spec.compile(), 4, HeightmapGrid())
    stack.renew(np.arange(4), np.random.default_rng(5))
    heights, res = stack.heights, config.resolution
    x = stack.layout.x_min + np.arange(stack.layout.ncol) * res
    rng = np.random.default_rng(0)
    which = rng.integers(0, 4, 4000)
    low = rng.uniform(-22.0, 22.0, 4000)
    high = low + rng.uniform(0.0, 3.0, 4000)
    level = stack.level(low, high, which)
    near = [(x >= lo - res) & (x <= hi + res) for lo, hi in zip(low, high, strict=True)]
    zero = np.array([not heights[i][:, n].any() for i, n in zip(which, near, strict=True)])
    assert level.any() and not (level & ~zero).any()
    inside = np.zeros(4000, bool)  # within a flat segment, a cell clear of its ends
    for i in range(4):
        for span in stack.plans[i]:
            if span.kind == "flat":
                start = x[span.c0] + (res if span.c0 else -50.0)
                end = x[span.c1] - 2 * res if span.c1 < len(x) - 1 else 50.0
                inside |= (which == i) & (low >= start) & (high <= end)
    assert inside.sum() > 200 and level[inside].all()


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


def test_top_is_the_highest_vertex_of_the_square() -> None:
    """`HeightStack.top`: the highest vertex within k cells of each point's nearest vertex (the
    square cut at the terrain's edges), where a box of half side k cells comes to rest."""
    rng = np.random.default_rng(0)
    layout = Terrain(rng.uniform(0, 1, (41, 61)).astype(np.float32))
    for grid in (None, HeightmapGrid()):  # unpadded and padded
        stack = HeightStack(layout, 2, grid)
        other = rng.uniform(0, 1, layout.heights.shape).astype(np.float32)
        stack.write(0, layout.heights)
        stack.write(1, other)
        xy = rng.uniform((-3.2, -2.2), (3.2, 2.2), (50, 2))  # beyond the edges too
        which = rng.integers(0, 2, 50)
        tops = stack.top(xy, 0.2, which)
        for (x, y), terrain, top in zip(xy, which, tops, strict=True):
            heights = (layout.heights, other)[terrain]
            c = int(np.clip(np.rint((x - layout.x_min) / 0.1), 0, 60))
            r = int(np.clip(np.rint((y - layout.y_min) / 0.1), 0, 40))
            square = heights[max(r - 2, 0) : r + 3, max(c - 2, 0) : c + 3]
            assert top == pytest.approx(square.max())


def test_a_plan_renders_the_same_in_pieces_and_framed() -> None:
    """`render` of any rectangles of a framed array, in any order, gives the terrain that
    `generate_terrain` draws, its frame repeating the edges."""
    config = TerrainConfig(size_x=40.0, size_y=6.0, start_flat=4.0, obstacles=("rubble", "hills"))
    rng = np.random.default_rng(5)
    margin = 7
    for seed in (0, 2, 3):  # each with rubble
        spans = plan_terrain(config, np.random.default_rng(seed))
        terrain = generate_terrain(config, np.random.default_rng(seed))
        assert "rubble" in {s.kind for s in spans}
        nrow, ncol = terrain.nrow + 2 * margin, terrain.ncol + 2 * margin
        out = np.full((nrow, ncol), -1.0, np.float32)
        row_cuts = np.unique(np.r_[0, rng.integers(1, nrow, 4), nrow])
        col_cuts = np.unique(np.r_[0, rng.integers(1, ncol, 6), ncol])
        blocks = list(itertools.product(itertools.pairwise(row_cuts), itertools.pairwise(col_cuts)))
        for k in rng.permutation(len(blocks)):
            render(spans, out, *blocks[k], margin=margin)
        framed = np.pad(terrain.heights, margin, mode="edge")
        np.testing.assert_array_equal(out, framed)
