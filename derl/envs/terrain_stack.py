"""Per-copy terrain for a batch: every copy walks its own heightfield, new for every episode.

A batch of simulations shares asset data such as ``hfield_data``, so each copy runs on its own
copy of the compiled model (`TerrainStack.models`, given to the batch). Each episode starts on a
fresh terrain, as in the released code (which rebuilt its model at every reset): it is drawn
straight into that copy's ``hfield_data``, where the physics reads it, and the heightmap
observation and the ground lookups read the same array (`HeightStack`, on the models' arrays):
one write of each terrain and no recompile. For the heightmap's sake the heightfield is padded
on every side by edge-valued cells (`derl.envs.heightmap.padding`): physically the world goes on
flat at its edge heights, where episodes have ended already.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import mujoco
import numpy as np

from derl.envs.heightmap import HeightmapGrid, HeightStack, padding, spread
from derl.envs.terrain import Terrain, TerrainConfig, draw_terrain

HFIELD_NAME = "terrain"
HFIELD_BASE = 0.1  # depth of the solid under z = 0, m


def add_hfield(spec: mujoco.MjSpec, config: TerrainConfig, grid: HeightmapGrid | None) -> None:
    """Add the terrain's heightfield asset (padded for ``grid``'s heightmap; all zeros until a
    terrain is written) and its geom, centred at the origin."""
    margin = padding(grid, config.resolution)
    nrow, ncol = (n + 2 * margin for n in config.grid_shape)
    edge = margin * config.resolution
    spec.add_hfield(
        name=HFIELD_NAME,
        nrow=nrow,
        ncol=ncol,
        size=[config.size_x / 2 + edge, config.size_y / 2 + edge, config.max_height, HFIELD_BASE],
        userdata=np.zeros(nrow * ncol, np.float32),
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
    """The terrains of ``count`` copies of ``model`` (built with `add_hfield`): their
    heightfields in the copies' own models, `models` (run copy i on models[i]), and
    `HeightStack`'s lookups on them.

    ``draw(rng)`` makes one terrain laid out like ``config``; by default the obstacle corridor
    of `derl.envs.terrain.generate_terrain` is drawn straight into the heightfield. ``grid`` is
    the heightmap that will be read from the stack (None: none), which sizes the padding.
    """

    def __init__(
        self,
        config: TerrainConfig,
        model: mujoco.MjModel,
        count: int,
        grid: HeightmapGrid | None,
        draw: Callable[[np.random.Generator], Terrain] | None = None,
    ) -> None:
        self.config = config
        self.draw = draw
        self.models = [copy.copy(model) for _ in range(count)]
        self.hfield = model.hfield(HFIELD_NAME).id
        adr = int(model.hfield_adr[self.hfield])
        shape = (int(model.hfield_nrow[self.hfield]), int(model.hfield_ncol[self.hfield]))
        arrays = [
            m.hfield_data[adr : adr + shape[0] * shape[1]].reshape(shape) for m in self.models
        ]
        layout = Terrain(
            np.zeros(config.grid_shape, np.float32), config.resolution, config.max_height
        )
        super().__init__(layout, arrays, grid, scale=config.max_height)
        self.first_obstacle = np.full(count, np.inf)
        """x where each copy's first obstacle starts (inf: none; -inf: anywhere)."""
        self.generated = 0

    def renew(self, ids: np.ndarray, rng: np.random.Generator) -> None:
        """A fresh terrain for each copy in ``ids``."""
        x_min, res = self.layout.x_min, self.layout.resolution
        for i in ids.tolist():
            if self.draw is not None:
                terrain = self.draw(rng)
                self.write(i, terrain.heights)
                self.first_obstacle[i] = terrain.first_obstacle
                continue
            spans = draw_terrain(self.config, rng, self.interior[i], 1.0 / self.scale)
            self.pad(i)
            changes = np.zeros(self.layout.ncol - 1, bool)  # columns c, c + 1 not one level
            obstacles = [(c0, c1) for kind, c0, c1, _ in spans if kind != "flat"]
            for c0, c1 in obstacles:
                changes[max(c0 - 1, 0) : c1] = True
            self.rough[i] = spread(changes, self.margin)
            self.first_obstacle[i] = x_min + obstacles[0][0] * res if obstacles else np.inf
        self.generated += len(ids)
