"""Clips that can be read: frames of FT, VT and MVT rendered offscreen (real MuJoCo, EGL) and
checked by their pixels (not black, a sky, a textured ground, the body in view while it moves
metres, close up and never end-on however it turns, an MVT box and goal in view with their
poles), the drawn terrain against the one the physics uses, the physics of a filmed copy against
an unfilmed one, and a GIF's colours against the frames'."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import mujoco
import numpy as np
import pytest

from derl.envs import make_task
from derl.envs.batched import EnvConfig, UnimalEnv
from derl.envs.film_set import COARSE_DROP, COARSE_STEP, FAR_TERRAIN
from derl.envs.terrain_stack import HFIELD_NAME
from derl.envs.video import FrameRecorder, write_video
from derl.unimal import Genome, Joint, Limb

WIDTH, HEIGHT = 240, 180
SPEED = 0.08
"""m per control step the body is carried along +x in the follow test (4 m/s)."""
ROLL = Joint(axis="y", range=(-30, 0), gear=150)


def _env(genome: Genome, task: str, seed: int = 3) -> UnimalEnv:
    env = UnimalEnv(genome, make_task(task), EnvConfig(num_envs=1, episode_steps=1000), seed=seed)
    env.reset(seed)
    return env


def _segments(recorder: FrameRecorder) -> np.ndarray:
    """(height, width) the geom id seen at each pixel (-1: none) of the frame just rendered."""
    renderer = recorder.renderer
    renderer.enable_segmentation_rendering()
    try:
        renderer.update_scene(recorder.set.data, recorder.camera)
        seen = renderer.render()
    finally:
        renderer.disable_segmentation_rendering()
    return np.where(seen[..., 1] == mujoco.mjtObj.mjOBJ_GEOM, seen[..., 0], -1)


def _body_geoms(model: mujoco.MjModel) -> np.ndarray:
    head = model.body("head").id
    bodies = [b for b in range(model.nbody) if model.body_rootid[b] == head]
    return np.flatnonzero(np.isin(model.geom_bodyid, bodies))


@pytest.mark.parametrize("task", ["ft", "vt", "mvt"])
def test_a_frame_is_lit_under_a_sky_on_a_textured_ground(quadruped: Genome, task: str) -> None:
    env = _env(quadruped, task)
    recorder = FrameRecorder(env, WIDTH, HEIGHT)
    try:
        for _ in range(5):
            env.step(np.zeros((1, env.model.nu)))
            frame = recorder.frame().astype(float)
        segments = _segments(recorder)
    finally:
        recorder.close()
    luminance = frame @ [0.299, 0.587, 0.114]
    assert np.mean(luminance < 40) < 0.02 and luminance.mean() > 120  # not black, not dim
    top = np.s_[: HEIGHT // 20]  # the top rows: the sky, but for a pole over a goal or a box
    sky = frame[top][segments[top] < 0]
    assert sky.size > 0.8 * frame[top].size
    assert np.all(sky[:, 2] > sky[:, 0]) and sky.mean() > 180  # a pale blue, not black
    ground = segments >= 0
    ground[np.isin(segments, _body_geoms(recorder.set.model))] = False
    lower = luminance[HEIGHT // 2 :][ground[HEIGHT // 2 :]]
    assert lower.size > WIDTH * HEIGHT // 4 and lower.std() > 12  # the checker's contrast
    bright, dark = np.percentile(lower, [90, 10])
    assert bright - dark > 30


@pytest.mark.parametrize("task", ["ft", "vt"])
def test_the_camera_follows_the_body_over_an_episode(quadruped: Genome, task: str) -> None:
    """The body is carried 8 m along +x; in every 10th frame it is seen, near the middle (the
    frames between are followed, not rendered, as in a clip of every 10th frame)."""
    env = _env(quadruped, task)
    recorder = FrameRecorder(env, WIDTH, HEIGHT)
    start = env.head_pos[0].copy()
    body = _body_geoms(recorder.set.model)
    try:
        for step in range(100):
            env.qpos[0, env.root] = start[0] + SPEED * (step + 1)
            env.qvel[0] = 0.0
            env.step(np.zeros((1, env.model.nu)))
            if step % 10 != 9:
                recorder.follow()
                continue
            recorder.frame()
            rows, cols = np.nonzero(np.isin(_segments(recorder), body))
            assert rows.size > 200, f"step {step}: the body is not in view"
            assert abs(cols.mean() / WIDTH - 0.5) < 0.25, f"step {step}: off centre"
            assert abs(rows.mean() / HEIGHT - 0.5) < 0.25, f"step {step}: off centre"
    finally:
        recorder.close()
    assert env.head_pos[0, 0] - start[0] > 7.5


def test_a_walk_is_filmed_close_and_across_the_body_however_it_turns() -> None:
    """A stick of a body (as the FT agent) held turned each way on FT: the camera, from behind and
    to a side, turns to see it across, close up; it never sees it end-on."""
    stick = Genome(
        head_density=600,
        limb_density=900,
        limbs=(Limb(id=0, paired=True, length=0.3, theta=90, phi=90, joints=(ROLL,)),),
    )
    env = _env(stick, "ft")
    recorder = FrameRecorder(env, WIDTH, HEIGHT)
    body = _body_geoms(recorder.set.model)
    start = env.qpos[0, env.root : env.root + 7].copy()
    try:
        for yaw in (0.0, -30.0, 45.0, 90.0):  # the stick's axis at 90, 60, 135 and 180 degrees
            half = np.radians(yaw) / 2
            turned = np.zeros(4)
            mujoco.mju_mulQuat(turned, [np.cos(half), 0, 0, np.sin(half)], start[3:])
            for _ in range(150):
                env.qpos[0, env.root + 3 : env.root + 7] = turned
                env.qvel[0] = 0.0
                env.step(np.zeros((1, env.model.nu)))
                recorder.follow()
            recorder.frame()
            cols = np.nonzero(np.isin(_segments(recorder), body))[1]
            assert np.ptp(cols) > 0.4 * WIDTH, f"turned {yaw}: {np.ptp(cols)} px wide"
    finally:
        recorder.close()


def test_mvt_shows_the_box_and_its_goal_then_the_goal_from_the_box(quadruped: Genome) -> None:
    """The body close up with the box 15-24 m ahead and its goal beyond, both marked by poles;
    once at the box, the goal."""
    env = _env(quadruped, "mvt", seed=0)  # seed 3's first terrain hides the box behind a hill
    recorder = FrameRecorder(env)  # full size: the goal is 30 m or more away
    model = recorder.set.model
    box = model.geom("box").id
    goal = set(np.flatnonzero(model.geom_bodyid == model.body("goal").id))
    marker = set(np.flatnonzero(model.geom_bodyid == model.body("object_marker0").id))
    try:
        for _ in range(25):  # the camera settles
            env.step(np.zeros((1, env.model.nu)))
            recorder.frame()
        segments = _segments(recorder)
        seen = set(np.unique(segments))
        assert box in seen and goal & seen and marker & seen
        cols = np.nonzero(np.isin(segments, _body_geoms(model)))[1]
        assert np.ptp(cols) > 0.15 * recorder.renderer.width  # the body close up, not afar
        (carried,) = recorder.set.objects
        floor = carried.position[0, 2] - carried.half
        at_box = [*(carried.position[0, :2] - [1.0, 0.0]), floor + env.rest_height + 0.05]
        for _ in range(25):  # the body held 1 m from the box: the camera turns to the goal
            env.qpos[0, env.root : env.root + 3] = at_box
            env.qvel[0] = 0.0
            env.step(np.zeros((1, env.model.nu)))
            recorder.frame()
        np.testing.assert_array_equal(recorder.set.focus(env.head_pos[0]), carried.goal[0])
        assert goal & set(np.unique(_segments(recorder)))
    finally:
        recorder.close()


def test_the_drawn_terrain_is_the_one_the_physics_uses(quadruped: Genome) -> None:
    """Vertical rays: on the detailed patch they meet the drawn ground where they meet copy 0's
    terrain, and the coarse ground lies under it; far from it, the coarse ground is the terrain
    at every coarse vertex."""
    env = _env(quadruped, "vt")
    recorder = FrameRecorder(env, WIDTH, HEIGHT)
    recorder.frame()
    recorder.close()
    film, data = recorder.set.model, recorder.set.data
    physics = env.task.arena.terrains.models[0]
    physics_data = mujoco.MjData(physics)
    mujoco.mj_forward(physics, physics_data)
    ground = physics.geom(HFIELD_NAME).id
    patch, far = film.geom(HFIELD_NAME).id, film.geom(FAR_TERRAIN).id
    rng = np.random.default_rng(0)

    def drop(model: mujoco.MjModel, data: mujoco.MjData, xy: np.ndarray, geom: int) -> float:
        """Height where a ray down through `xy` meets the heightfield `geom`."""
        distance = mujoco.mj_rayHfield(model, data, geom, [*xy, 10.0], [0.0, 0.0, -1.0])
        assert distance >= 0
        return 10.0 - distance

    centre, half = film.geom_pos[patch, :2], film.hfield(HFIELD_NAME).size[:2]
    for xy in centre + rng.uniform(-half, half, (50, 2)):
        detailed = drop(film, data, xy, patch)
        assert detailed == pytest.approx(drop(physics, physics_data, xy, ground), abs=1e-9)
        assert drop(film, data, xy, far) <= detailed - COARSE_DROP + 1e-9
    spacing = COARSE_STEP * env.task.arena.terrains.config.resolution
    for xy in np.round(rng.uniform([10, -40], [45, 40], (30, 2)) / spacing) * spacing:
        expected = drop(physics, physics_data, xy, ground) - COARSE_DROP
        assert drop(film, data, xy, far) == pytest.approx(expected, abs=1e-6)


def test_filming_leaves_the_physics_alone(quadruped: Genome) -> None:
    """A filmed copy and an unfilmed one, same seed and actions: the same states, bit for bit;
    the filmed set shows the body where the physics has it."""
    states = []
    for filmed in (False, True):
        env = _env(quadruped, "mvt")
        actions = np.random.default_rng(1).uniform(-1, 1, (30, 1, env.model.nu))
        recorder = FrameRecorder(env, WIDTH, HEIGHT) if filmed else None
        for action in actions:
            env.step(action)
            if recorder is not None:
                recorder.frame()
        states.append(env.qpos.copy())
        if recorder is not None:
            head = recorder.set.data.xpos[recorder.set.model.body("head").id]
            np.testing.assert_array_equal(head, env.head_pos[0])
            recorder.close()
    np.testing.assert_array_equal(*states)


def test_a_clip_of_every_nth_frame_is_every_nth_frame_of_the_whole_clip(quadruped: Genome) -> None:
    """`derl rollout --video-every N` renders only the frames it keeps: the camera still follows
    the body at every step, so each kept frame is the one a clip of every frame would have."""
    clips = []
    for every in (1, 3):
        env = _env(quadruped, "vt")
        rng = np.random.default_rng(0)
        recorder = FrameRecorder(env, 64, 48)
        frames = []
        try:
            for step in range(12):
                if step % every == 0:
                    frames.append(recorder.frame())
                else:
                    recorder.follow()
                env.step(rng.uniform(-1, 1, (1, env.model.nu)))
        finally:
            recorder.close()
        clips.append(frames)
    whole, kept = clips
    assert len(kept) == 4
    for frame, expected in zip(kept, whole[::3], strict=True):
        assert np.array_equal(frame, expected)


def test_a_gif_keeps_every_colour_near_its_own(quadruped: Genome, tmp_path: Path) -> None:
    """A GIF has 256 colours a frame: small parts (the head, a far goal's pole) keep theirs, every
    pixel within 20 of its level in each channel (Pillow's default palette greyed them by 50)."""
    env = _env(quadruped, "mvt", seed=0)
    recorder = FrameRecorder(env, WIDTH, HEIGHT)
    try:
        frames = []
        for _ in range(3):
            env.step(np.zeros((1, env.model.nu)))
            frames.append(recorder.frame())
    finally:
        recorder.close()
    write_video(tmp_path / "clip.gif", frames)
    back = iio.imread(tmp_path / "clip.gif")[..., :3].astype(int)
    assert np.abs(back - np.array(frames, dtype=int)).max() <= 20
