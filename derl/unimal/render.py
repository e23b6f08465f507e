"""Offscreen pictures of bodies: one body standing on a floor, or a population as a grid.

MuJoCo picks its OpenGL backend from the environment variable ``MUJOCO_GL`` when it is first
imported: ``egl`` (Mesa or a GPU driver) or ``osmesa`` (software) render without a display.
The ``derl`` command sets ``MUJOCO_GL=egl`` unless it is set already.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np

from derl.unimal.genome import Genome
from derl.unimal.geometry import bounding_box, layout
from derl.unimal.mjcf import standalone_spec

GRID_GAP = 4


def offscreen_renderer(model: mujoco.MjModel, width: int, height: int) -> mujoco.Renderer:
    """A renderer of `model`; `RuntimeError` with the remedy when offscreen OpenGL is missing."""
    try:
        return mujoco.Renderer(model, height, width)
    except Exception as error:  # no usable OpenGL backend
        raise RuntimeError(
            "offscreen rendering is not available: set MUJOCO_GL=egl (Mesa EGL or a GPU driver) "
            f"or MUJOCO_GL=osmesa (Debian's libosmesa6) before starting Python ({error})"
        ) from error


def render_body(genome: Genome, width: int = 320, height: int = 240) -> np.ndarray:
    """An RGB image (height, width, 3) of the body at rest, seen from the front left."""
    model = standalone_spec(genome).compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    low, high = bounding_box(layout(genome))
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    head = data.xpos[model.body("head").id]
    camera.lookat[:] = head + (low + high) / 2
    camera.distance = 1.2 * float(np.linalg.norm(high - low)) + 0.6
    camera.azimuth = 135.0
    camera.elevation = -20.0
    with offscreen_renderer(model, width, height) as renderer:
        renderer.update_scene(data, camera)
        return renderer.render().copy()


def render_grid(
    genomes: list[Genome], width: int = 240, height: int = 180, columns: int | None = None
) -> np.ndarray:
    """Pictures of several bodies tiled row by row on a white background."""
    columns = columns or math.ceil(math.sqrt(len(genomes)))
    rows = math.ceil(len(genomes) / columns)
    grid = np.full(
        (rows * (height + GRID_GAP) - GRID_GAP, columns * (width + GRID_GAP) - GRID_GAP, 3),
        255,
        dtype=np.uint8,
    )
    for index, genome in enumerate(genomes):
        row, column = divmod(index, columns)
        top, left = row * (height + GRID_GAP), column * (width + GRID_GAP)
        grid[top : top + height, left : left + width] = render_body(genome, width, height)
    return grid


def save_png(image: np.ndarray, path: Path) -> None:
    import matplotlib.image

    path.parent.mkdir(parents=True, exist_ok=True)
    matplotlib.image.imsave(path, image)
