"""Clips of copy 0 of a batched environment: the body on a dressed set (`derl.envs.film_set`)
seen by a camera that follows it, and the frames written as a video."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import mujoco
import numpy as np

from derl.envs.batched import UnimalEnv
from derl.envs.film_set import FilmSet
from derl.unimal.render import offscreen_renderer

FPS = 50 // 2
"""Frames per second of a video: every control step is 20 ms, played at half speed."""
FOLLOW = 0.08
"""Share of the way left to where it should be that the camera moves each frame, besides keeping
up with the body's speed (smoothed as much): the body's bobbing does not shake the picture."""
SPAN = 0.6
"""Share of the frame's width the body's span (its widest extent at the first frame, with
`THICKNESS` at each end) fills, seen across."""
THICKNESS = 0.1
"""About a limb's radius, m: the body's points are its limbs' axes."""
CLOSEST = 1.0
"""The camera comes no closer to the body's centre than this, m."""
SIDES = np.concatenate([np.arange(-70.0, -19.0), np.arange(20.0, 71.0)])
"""A walk (along +x) is filmed from behind and to a side, looking this many degrees to the left
of it: of these, from where the body looks widest (its points' spread across the view), so never
end-on; the side it is on is kept while the other is not much better (`STAY`)."""
STAY = 0.1
SHAPE_FOLLOW = 0.02
"""Share of the body's present shape that its remembered shape takes each frame (about 1 s)."""
ELEVATION = -20.0
ELEVATIONS = np.arange(-45.0, -8.0, 3.0)
"""A body with a target is seen with it from one of these elevations: the nearest view, a higher
one unless a lower one is `CLOSER` (a higher view shows more of the ground between them)."""
CLOSER = 0.8
FARTHEST = 2.5
"""The camera holds the body and the set's marks from no farther than this many times its
distance on a walk (the body then fills 0.24 of the frame's width)."""
BEHIND = 20.0
"""A body with a target is seen from behind it, this many degrees to its right."""
MARGIN = 0.1
"""Share of the frame kept free at each edge when the body is framed with its target."""
MARK_RADIUS = 0.3
"""What must be in view around each of the set's marks (`FilmSet.marks`), m."""


class FrameRecorder:
    """Renders copy 0 of `env` after each call; uses `MUJOCO_GL` (egl or osmesa); `RuntimeError`
    when offscreen OpenGL is missing.

    The camera follows the body's centre at a distance that makes its span `SPAN` of the frame.
    On a walk along +x it looks from the side and behind, turning to where the body looks widest;
    with a target to reach (`FilmSet.focus`) it looks from behind the body towards the target
    and frames both, from as near as it can."""

    def __init__(self, env: UnimalEnv, width: int = 480, height: int = 360) -> None:
        self.set = FilmSet(env)
        self.renderer = offscreen_renderer(self.set.model, width, height)
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_FOG] = True
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        half_fov = np.radians(self.set.model.vis.global_.fovy / 2)
        self.tan_half = np.array([np.tan(half_fov) * width / height, np.tan(half_fov)])
        self.radius = self.near = 0.0
        """The body's radius (half its span at the first frame, and `THICKNESS`) and the camera's
        distance from its centre on a walk, m."""
        self.shape = np.zeros((2, 2))
        """The body's points' spread on the ground, smoothed (`SHAPE_FOLLOW`)."""
        self.target: np.ndarray | None = None
        """The body's centre, smoothed: what the camera follows, and the terrain patch too. It
        moves at the centre's speed, smoothed, and `FOLLOW` of the way left: it keeps up with a
        body at a steady speed (no lag) and does not shake with its bobbing."""
        self.centre, self.velocity = np.zeros(3), np.zeros(3)
        """The body's centre at the last frame and its speed (m a frame), smoothed."""

    def frame(self) -> np.ndarray:
        """An RGB image (height, width, 3) of copy 0 now (the camera `follow`s it first)."""
        self.follow()
        for hfield in self.set.take_uploads():
            self.renderer._gl_context.make_current()  # the Renderer has no public upload call
            mujoco.mjr_uploadHField(self.set.model, self.renderer._mjr_context, hfield)
        self.renderer.update_scene(self.set.data, self.camera)
        return self.renderer.render().copy()

    def follow(self) -> None:
        """Move the camera one frame's way after copy 0, without rendering (a frame skipped: the
        camera moves as smoothly as in a clip of every frame)."""
        head = self.set.pose(self.target)
        points = self.set.env.agent_points()[0]
        centre = (points.min(axis=0) + points.max(axis=0)) / 2
        spread = points[:, :2] - points[:, :2].mean(axis=0)
        camera = self.camera
        if self.target is None:  # the first frame: the camera starts where it is to be
            span = np.max(np.linalg.norm(points[:, None] - points[None], axis=-1))
            self.radius = float(span) / 2 + THICKNESS
            self.near = max(CLOSEST, 2 * self.radius / (SPAN * 2 * self.tan_half[0]))
            self.target, self.centre, share = centre.copy(), centre, 1.0
            self.shape = spread.T @ spread
            camera.azimuth = float(np.mean(np.abs(SIDES)))
        else:
            self.velocity += FOLLOW * (centre - self.centre - self.velocity)
            self.target += self.velocity + FOLLOW * (centre - self.target)
            self.centre = centre
            self.shape += SHAPE_FOLLOW * (spread.T @ spread - self.shape)
            share = FOLLOW
        focus = self.set.focus(head)
        if focus is None:
            azimuth, view = self._side(camera.azimuth), (self.target, self.near, ELEVATION)
        else:
            azimuth = BEHIND + float(np.degrees(np.arctan2(*(focus - centre)[1::-1])))
            view = self._framed(self.target, self.set.marks(head), azimuth)
        camera.azimuth += share * ((azimuth - camera.azimuth + 180.0) % 360.0 - 180.0)
        lookat, distance, elevation = view
        camera.lookat[:] += self.velocity + share * (lookat - camera.lookat - self.velocity)
        camera.distance += share * (distance - camera.distance)
        camera.elevation += share * (elevation - camera.elevation)

    def _side(self, now: float) -> float:
        """The azimuth of `SIDES` from which the body, as it has looked of late, is widest, those
        near `now` (the camera's) favoured by `STAY`."""
        sides = np.radians(SIDES)
        across = np.stack([-np.sin(sides), np.cos(sides)])  # across the view, on the ground
        width = np.einsum("in,ij,jn->n", across, self.shape, across)
        return float(SIDES[np.argmax(width * (1 + STAY * np.cos(sides - np.radians(now))))])

    def _framed(
        self, body: np.ndarray, marks: np.ndarray, azimuth: float
    ) -> tuple[np.ndarray, float, float]:
        """(lookat, distance, elevation) of the nearest view from `azimuth` that holds the body
        (a sphere of `radius` at `body`) and as many of `marks` (`FilmSet.marks`: the first, the
        first two ...) as it can from no farther than `FARTHEST` times `near`, each a sphere of
        `MARK_RADIUS`, inside `MARGIN`; the body's view when it holds none."""
        shares = np.linspace(0.0, 1.0, 11)[:, None]
        distances = np.geomspace(self.near, 2 * FARTHEST * self.near, 16)
        for held in range(len(marks), 0, -1):
            points = marks[:held]
            lookat = body + shares * (points.mean(axis=0) - body)  # (W, 3)
            best = (body, self.near, ELEVATION, np.inf)
            for elevation in ELEVATIONS:
                forward, right, up = _axes(azimuth, elevation)
                eye = lookat[:, None] - distances[None, :, None] * forward  # (W, D, 3)
                fits = _inside(body, self.radius, eye, forward, right, up, self.tan_half)
                for point in points:
                    fits &= _inside(point, MARK_RADIUS, eye, forward, right, up, self.tan_half)
                depth = np.where(fits, (body - eye) @ forward, np.inf)
                w, d = np.unravel_index(np.argmin(depth), depth.shape)
                if depth[w, d] < CLOSER * best[3]:
                    best = (lookat[w], float(distances[d]), float(elevation), float(depth[w, d]))
            if best[3] <= FARTHEST * self.near:
                return best[:3]
        return body, self.near, ELEVATION

    def close(self) -> None:
        self.renderer.close()


def _axes(azimuth: float, elevation: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A free camera's forward, right and up vectors (MuJoCo's `mjv_updateCamera`)."""
    a, e = np.radians(azimuth), np.radians(elevation)
    forward = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    up = np.array([-np.sin(e) * np.cos(a), -np.sin(e) * np.sin(a), np.cos(e)])
    return forward, np.cross(forward, up), up


def _inside(
    point: np.ndarray,
    radius: float,
    eye: np.ndarray,
    forward: np.ndarray,
    right: np.ndarray,
    up: np.ndarray,
    tan_half: np.ndarray,
) -> np.ndarray:
    """Whether a sphere at `point` is seen from each of `eye` (..., 3) inside `MARGIN` of the
    frame's edges."""
    seen = point - eye
    depth = seen @ forward
    limit = (1.0 - MARGIN) * depth[..., None] * tan_half
    off = np.abs(np.stack([seen @ right, seen @ up], axis=-1)) + radius
    return (depth > radius) & np.all(off <= limit, axis=-1)


class VideoError(ValueError):
    """A video that cannot be written there, with the reason, and the exit status it means:
    2 for a format derl does not write, 1 for a folder or a missing extra."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def check_video_path(path: Path) -> None:
    """`VideoError` unless `write_video` can write `path`: a .gif, or an .mp4 with
    imageio-ffmpeg installed, in a folder that exists, where the file can be made (tried: the
    permissions do not say it for root, nor on /proc or a read-only file system)."""
    if path.suffix not in (".gif", ".mp4"):
        raise VideoError(f"{path}: write a .gif, or an .mp4 (pip install 'derl[video]')", 2)
    if path.suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise VideoError(f"{path}: an .mp4 needs imageio-ffmpeg (pip install 'derl[video]')", 1)
    folder = path.parent
    if not folder.is_dir():
        raise VideoError(f"{path}: no folder {folder}", 1)
    existed = path.exists()
    try:
        with path.open("ab"):
            pass
    except OSError as error:
        why = (error.strerror or str(error)).lower()
        raise VideoError(f"{path}: cannot write there ({why})", 1) from None
    if not existed:
        path.unlink()


def write_video(path: Path, frames: list[np.ndarray], fps: int = FPS) -> None:
    """`frames` as an .mp4 (needs imageio-ffmpeg) or, for a .gif path, a looping GIF; `OSError`
    with the reason and the remedy when it cannot be written. A GIF frame's 256 colours are
    Pillow's octree palette: its default (median cut) greyed what few pixels have (a far pole,
    the body's head)."""
    import imageio.v3 as iio
    from PIL import Image

    try:
        if path.suffix == ".gif":
            images = [Image.fromarray(frame).quantize(method=Image.Quantize.FASTOCTREE)
                      for frame in frames]  # fmt: skip
            images[0].save(path, save_all=True, append_images=images[1:], duration=1000 / fps,
                           loop=0)  # fmt: skip
        else:
            iio.imwrite(path, frames, fps=fps)
    except (ImportError, ValueError, OSError) as error:
        raise OSError(
            f"cannot write {path}: {error}. For .mp4 install imageio-ffmpeg "
            "(pip install 'derl[video]'), or ask for a .gif"
        ) from None
