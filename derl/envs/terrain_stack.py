"""Per-copy terrain for a batch: every copy walks its own heightfield, new for every episode.

A batch of simulations shares asset data such as ``hfield_data``, so each copy runs on its own
copy of the compiled model (`TerrainStack.models`, given to the batch). Each episode starts on a
fresh terrain, as in the released code (which rebuilt its model at every reset), without
recompiling: it is written into a stacked height array (`HeightStack`), where the heightmap
observation and the ground lookups read all copies' terrains in one gather each, and copied into
that copy's ``hfield_data``, where the physics reads it. The heightfield is padded on every side
as the stack is (`derl.envs.heightmap.padding`): physically the world goes on flat at its edge
heights, where episodes have ended already, and one copy of a stretch serves both.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable

import mujoco
import numpy as np

from derl.envs.heightmap import HeightmapGrid, HeightStack, padding, spread
from derl.envs.terrain import Span, Terrain, TerrainConfig, plan_terrain, render

HFIELD_NAME = "terrain"
HFIELD_BASE = 0.1  # depth of the solid under z = 0, m
STRETCH = 2.0  # m: a lazily written corridor is written this far beyond what is needed now


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
    """The terrains of ``count`` copies of ``model`` (built with `add_hfield`): `HeightStack`'s
    lookups on them, and their heightfields in the copies' own models, `models` (run copy i on
    models[i]).

    ``draw(rng)`` makes one terrain laid out like ``config``; by default the obstacle corridor
    of `derl.envs.terrain.generate_terrain` is planned (`plan_terrain`: its draws) and written
    stretch by stretch (`render`). With ``ahead`` (m), a corridor's columns are written only as
    far as they can be touched or seen: ``ahead`` beyond each point of the copy that is read
    (`ground`, `top`) or tracked (`reach`), plus `STRETCH`. ``grid`` is the heightmap that will
    be read from the stack (None: none), which sizes the padding.
    """

    def __init__(
        self,
        config: TerrainConfig,
        model: mujoco.MjModel,
        count: int,
        grid: HeightmapGrid | None,
        draw: Callable[[np.random.Generator], Terrain] | None = None,
        ahead: float | None = None,
    ) -> None:
        layout = Terrain(
            np.zeros(config.grid_shape, np.float32), config.resolution, config.max_height
        )
        super().__init__(layout, count, grid, scale=config.max_height)
        self.config = config
        self.draw = draw
        self.models = [copy.copy(model) for _ in range(count)]
        self.hfield = model.hfield(HFIELD_NAME).id
        adr, size = int(model.hfield_adr[self.hfield]), self.padded[0].size
        shape = (int(model.hfield_nrow[self.hfield]), int(model.hfield_ncol[self.hfield]))
        if shape != self.padded.shape[1:]:
            raise ValueError(f"heightfield of {shape} vertices, not {self.padded.shape[1:]}")
        self._hfields = [m.hfield_data[adr : adr + size].reshape(shape) for m in self.models]
        self.ahead = None if ahead is None else math.ceil(ahead / config.resolution)  # columns
        self._stretch = round(STRETCH / config.resolution)
        self.plans: list[list[Span]] = [[] for _ in range(count)]
        self.written = np.full(count, layout.ncol)
        """Columns of each copy's terrain written so far (from column 0)."""
        self.first_obstacle = np.full(count, np.inf)
        """x where each copy's first obstacle starts (inf: none; -inf: anywhere)."""
        self.generated = 0

    def renew(self, ids: np.ndarray, rng: np.random.Generator) -> None:
        """A fresh terrain for each copy in ``ids``."""
        x_min, res, ncol = self.layout.x_min, self.layout.resolution, self.layout.ncol
        for i in ids.tolist():
            if self.draw is not None:
                terrain = self.draw(rng)
                self.write(i, terrain.heights)
                self._hfields[i][:] = self.padded[i]
                self.first_obstacle[i] = terrain.first_obstacle
                continue
            self.plans[i] = spans = plan_terrain(self.config, rng)
            self.written[i] = 0
            changes = np.zeros(ncol - 1, bool)  # columns c and c + 1 not both at one level
            obstacles = [(s.c0, s.c1) for s in spans if s.kind != "flat"]
            for c0, c1 in obstacles:
                changes[max(c0 - 1, 0) : c1] = True
            self.rough[i] = spread(changes, self.margin)
            self.first_obstacle[i] = x_min + obstacles[0][0] * res if obstacles else np.inf
            if self.ahead is None:
                self._write_columns(i, ncol)
        self.generated += len(ids)

    def reach(self, x: np.ndarray, which: np.ndarray | None = None) -> None:
        """Write the terrain of copy ``which[k]`` (default: k) as far as `ahead` beyond ``x[k]``
        (m) if it is not yet: call it with where each body is after every step."""
        if self.ahead is None:
            return
        which = self._terrains[: len(x)] if which is None else which
        need = (x - self.layout.x_min) / self.layout.resolution + self.ahead
        for k in np.flatnonzero(need > self.written[which]).tolist():
            self._write_columns(int(which[k]), int(need[k]) + self._stretch)

    def ground(self, xy: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
        self.reach(xy[:, 0], which)
        return super().ground(xy, which)

    def top(self, xy: np.ndarray, half: float, which: np.ndarray | None = None) -> np.ndarray:
        self.reach(xy[:, 0] + half, which)
        return super().top(xy, half, which)

    def complete(self, i: int) -> None:
        """Write the rest of copy ``i``'s terrain (to show or check all of it)."""
        self._write_columns(i, self.layout.ncol)

    @property
    def heights(self) -> np.ndarray:
        for i in range(len(self.padded)):
            self.complete(i)
        return super().heights

    def _write_columns(self, i: int, stop: int) -> None:
        """Write copy ``i``'s planned terrain up to column ``stop`` (excluded), in the stack and
        in its heightfield."""
        start, stop = int(self.written[i]), min(stop, self.layout.ncol)
        if stop <= start:
            return
        render(self.plans[i], self.interior[i], start, stop, 1.0 / self.scale)
        self.pad(i, start, stop)
        m, ncol = self.margin, self.layout.ncol
        columns = slice(0 if start == 0 else m + start, None if stop == ncol else m + stop)
        self._hfields[i][:, columns] = self.padded[i][:, columns]
        self.written[i] = stop
