"""Offscreen frames of copy 0 of a batched environment, with a camera that follows the head, and
those frames written as a video."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from derl.envs.batched import UnimalEnv
from derl.unimal.render import offscreen_renderer

FPS = 50 // 2
"""Frames per second of a video: every control step is 20 ms, played at half speed."""


class FrameRecorder:
    """Renders copy 0 of `env` after each call; uses `MUJOCO_GL` (egl or osmesa); `RuntimeError`
    when offscreen OpenGL is missing."""

    def __init__(self, env: UnimalEnv, width: int = 480, height: int = 360) -> None:
        self.env = env
        terrains = getattr(env.task.arena, "terrains", None)
        self.model = terrains.models[0] if terrains is not None else env.model
        self.data = mujoco.MjData(self.model)
        self.renderer = offscreen_renderer(self.model, width, height)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        self.camera.trackbodyid = env.head
        self.camera.distance = 3.0 + 2.0 * env.rest_height
        self.camera.azimuth = 120.0
        self.camera.elevation = -20.0
        self.uploaded = -1

    def frame(self) -> np.ndarray:
        """An RGB image (height, width, 3) of copy 0 now."""
        terrains = getattr(self.env.task.arena, "terrains", None)
        if terrains is not None and terrains.generated != self.uploaded:
            # the copy's terrain changed: send all of it to the GPU (the Renderer has no public
            # call)
            terrains.complete(0)
            self.renderer._gl_context.make_current()
            mujoco.mjr_uploadHField(self.model, self.renderer._mjr_context, terrains.hfield)
            self.uploaded = terrains.generated
        self.env.batch.get_data(0, self.data)
        mujoco.mj_forward(self.model, self.data)
        self.renderer.update_scene(self.data, self.camera)
        return self.renderer.render().copy()

    def close(self) -> None:
        self.renderer.close()


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
