"""Per-copy terrain for a batch: every copy walks its own heightfield, new for each episode.

A batch of simulations shares asset data such as ``hfield_data``, so each copy runs on its own
shallow copy of the compiled model (`TerrainStack.models`, given to the batch); a new terrain
is written into that copy's ``hfield_data`` in place (no recompile) and into a stacked, padded
height array (`HeightStack`) that the heightmap observation and the fall test read for all copies
at once.

A terrain is renewed after every episode in which its copy could have perceived or touched an
obstacle: the head came within `reach` m (the heightmap's range plus a body's size) of the first
non-flat segment. An episode that saw only the flat start area learnt nothing about its terrain,
so the next one may use it as fresh: early in training, when bodies fall within a few dozen
steps, this avoids generating a million-cell terrain for each of them.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from functools import partial

import mujoco
import numpy as np

from derl.envs.heightmap import HeightmapGrid, HeightStack
from derl.envs.terrain import Terrain, TerrainConfig, generate_terrain

HFIELD_NAME = "terrain"
HFIELD_BASE = 0.1  # depth of the solid under z = 0, m


def add_hfield(spec: mujoco.MjSpec, config: TerrainConfig) -> None:
    """Add the terrain's heightfield asset and geom (all zeros until a terrain is written)."""
    nrow, ncol = config.grid_shape
    spec.add_hfield(
        name=HFIELD_NAME,
        nrow=nrow,
        ncol=ncol,
        size=[config.size_x / 2, config.size_y / 2, config.max_height, HFIELD_BASE],
        userdata=np.zeros(nrow * ncol).tolist(),
    )
    spec.worldbody.add_geom(
        name=HFIELD_NAME,
        type=mujoco.mjtGeom.mjGEOM_HFIELD,
        hfieldname=HFIELD_NAME,
        rgba=[0.55, 0.6, 0.5, 1],
        condim=3,
        friction=[0.7, 0.1, 0.1],
    )


class TerrainStack(HeightStack):
    """The terrains of ``count`` copies of ``model`` (their heights, `HeightStack`'s lookups on
    them), and their heightfields in the copies' own models, `models` (run copy i on models[i]).

    ``draw(rng)`` makes one terrain laid out like ``config`` (default: the obstacle corridor of
    `generate_terrain`); its segments tell where its obstacles start. ``grid`` is the heightmap
    that will be read from the stack (it sizes the padding).
    """

    def __init__(
        self,
        config: TerrainConfig,
        model: mujoco.MjModel,
        count: int,
        grid: HeightmapGrid,
        draw: Callable[[np.random.Generator], Terrain] | None = None,
    ) -> None:
        layout = Terrain(
            np.zeros(config.grid_shape, np.float32), config.resolution, config.max_height
        )
        super().__init__(layout, count, grid)
        self.config = config
        self.draw = draw or partial(generate_terrain, config)
        self.models = [copy.copy(model) for _ in range(count)]
        self.hfield = model.hfield(HFIELD_NAME).id
        self.first_obstacle = np.full(count, -np.inf)  # x where each copy's course starts
        self.furthest = np.full(count, np.inf)  # furthest head x in the current episode
        self.generated = 0

    def track(self, head_x: np.ndarray) -> None:
        """Record how far each copy's head went (call every step)."""
        np.maximum(self.furthest, head_x, out=self.furthest)

    def renew(self, ids: np.ndarray, rng: np.random.Generator, reach: float) -> None:
        """A fresh terrain for each copy in ``ids`` whose episode came within ``reach`` m of an
        obstacle (or that has none yet)."""
        seen = ids[self.furthest[ids] + reach >= self.first_obstacle[ids]]
        for i in seen:
            terrain = self.draw(rng)
            terrain.write_to(self.models[i], self.hfield)
            self.write(i, terrain.heights)
            self.first_obstacle[i] = terrain.first_obstacle
        self.generated += len(seen)
        self.furthest[ids] = -np.inf

    def forget(self) -> None:
        """Make every copy's next reset draw a fresh terrain (a new seeded run)."""
        self.furthest[:] = np.inf
