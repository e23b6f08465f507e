"""Clips of copy 0 of a batched environment: the body on a dressed set (`derl.envs.film_set`)
seen by a camera that follows it, and the frames written as a video."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import mujoco
import numpy as np

from derl.envs.batched import UnimalEnv
from derl.envs.film_set import FilmSet
from derl.unimal.render import offscreen_renderer

FPS = 50 // 2
"""Frames per second of a video: every control step is 20 ms, played at half speed."""
FOLLOW = 0.08
"""Share of the way to the head that the camera's target moves each frame (a lag of about
0.25 s at 50 frames a second: the body's bobbing does not shake the picture)."""
SIDE, BEHIND = 60.0, 20.0
"""The camera looks this many degrees to the left of where the body is going, from behind its
right: from the side (a gait is best read there) when it walks along +x; from nearly behind
when it has an object or a goal to reach, which then stays in view."""
ELEVATION = -18.0


class FrameRecorder:
    """Renders copy 0 of `env` after each call; uses `MUJOCO_GL` (egl or osmesa); `RuntimeError`
    when offscreen OpenGL is missing."""

    def __init__(self, env: UnimalEnv, width: int = 480, height: int = 360) -> None:
        self.set = FilmSet(env)
        self.renderer = offscreen_renderer(self.set.model, width, height)
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_FOG] = True
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.distance = 2.5 + 2.5 * env.rest_height
        self.camera.elevation = ELEVATION
        self.target: np.ndarray | None = None

    def frame(self) -> np.ndarray:
        """An RGB image (height, width, 3) of copy 0 now (the camera `follow`s it first)."""
        self.follow()
        for hfield in self.set.take_uploads():
            self.renderer._gl_context.make_current()  # the Renderer has no public upload call
            mujoco.mjr_uploadHField(self.set.model, self.renderer._mjr_context, hfield)
        self.camera.lookat[:] = self.target
        self.renderer.update_scene(self.set.data, self.camera)
        return self.renderer.render().copy()

    def follow(self) -> None:
        """Move the camera one frame's way after copy 0, without rendering (a frame skipped: the
        camera moves as smoothly as in a clip of every frame)."""
        head = self.set.pose(self.target)
        focus = self.set.focus(head)
        if focus is None:
            azimuth = SIDE
        else:
            azimuth = BEHIND + float(np.degrees(np.arctan2(*(focus - head)[1::-1])))
        if self.target is None:
            self.target, self.camera.azimuth = head, azimuth
        else:
            self.target += FOLLOW * (head - self.target)
            turn = (azimuth - self.camera.azimuth + 180.0) % 360.0 - 180.0
            self.camera.azimuth += FOLLOW * turn

    def close(self) -> None:
        self.renderer.close()


class VideoError(ValueError):
    """A video that cannot be written there, with the reason, and the exit status it means:
    2 for a format derl does not write, 1 for a folder or a missing extra."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def check_video_path(path: Path) -> None:
    """`VideoError` unless `write_video` can write `path`: a .gif, or an .mp4 with
    imageio-ffmpeg installed, in a folder that exists and can be written in."""
    if path.suffix not in (".gif", ".mp4"):
        raise VideoError(f"{path}: write a .gif, or an .mp4 (pip install 'derl[video]')", 2)
    if path.suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise VideoError(f"{path}: an .mp4 needs imageio-ffmpeg (pip install 'derl[video]')", 1)
    folder = path.parent
    if not folder.is_dir():
        raise VideoError(f"{path}: no folder {folder}", 1)
    if not os.access(folder, os.W_OK | os.X_OK) or (path.exists() and not path.is_file()):
        raise VideoError(f"{path}: cannot write there (permission denied)", 1)


def write_video(path: Path, frames: list[np.ndarray], fps: int = FPS) -> None:
    """`frames` as an .mp4 (needs imageio-ffmpeg) or, for a .gif path, a looping GIF; `OSError`
    with the reason and the remedy when it cannot be written."""
    import imageio.v3 as iio

    try:
        if path.suffix == ".gif":
            iio.imwrite(path, frames, duration=1000 / fps, loop=0)
        else:
            iio.imwrite(path, frames, fps=fps)
    except (ImportError, ValueError, OSError) as error:
        raise OSError(
            f"cannot write {path}: {error}. For .mp4 install imageio-ffmpeg "
            "(pip install 'derl[video]'), or ask for a .gif"
        ) from None
