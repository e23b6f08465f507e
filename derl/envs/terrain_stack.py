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
    a rectangle at a time (`render`). With ``ahead`` (m), a corridor is written only where it can
    be touched or seen: from its back edge to ``ahead`` beyond, and to ``ahead`` on either side
    of, each point of the copy that is read (`ground`, `top`) or tracked (`reach`), plus
    `STRETCH`. ``grid`` is the heightmap that will be read from the stack (None: none), which
    sizes the padding.
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
        super().__init__(layout, count, grid)
        self.config = config
        self.draw = draw
        self.models = [copy.copy(model) for _ in range(count)]
        self.hfield = model.hfield(HFIELD_NAME).id
        shape = self.padded.shape[1:]
        if (model.hfield_nrow[self.hfield], model.hfield_ncol[self.hfield]) != shape:
            raise ValueError(f"the heightfield is not {shape} vertices: build it with add_hfield")
        adr, size = int(model.hfield_adr[self.hfield]), self.padded[0].size
        self._hfields = [m.hfield_data[adr : adr + size].reshape(shape) for m in self.models]
        self._normalise = np.float32(1.0 / config.max_height)  # heightfield data: in [0, 1]
        self.ahead = None if ahead is None else math.ceil(ahead / config.resolution)  # cells
        self._reach_base = np.array([self.margin + (self.ahead or 0) + 1, self.margin], np.int32)
        self._stretch = round(STRETCH / config.resolution)
        self.plans: list[list[Span]] = [[] for _ in range(count)]
        self.written = np.zeros((count, 3), np.intp)
        """Each copy's written rectangle of `padded`: columns [0, c), rows [r0, r1): (c, r0, r1)."""
        self.written[:] = (shape[1], 0, shape[0])
        self._changes_before = np.tile(np.arange(self.layout.ncol, dtype=np.int32), (count, 1))
        """Per copy and terrain column c, how many of the strips between columns c' and c' + 1
        (c' < c) are not level at z = 0 (`level`); every strip until a planned terrain says."""
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
                np.multiply(self.padded[i], self._normalise, out=self._hfields[i])
                self.first_obstacle[i] = terrain.first_obstacle
                continue
            self.plans[i] = spans = plan_terrain(self.config, rng)
            self.written[i] = (0, self.padded.shape[1], 0)  # nothing
            changes = np.zeros(ncol - 1, bool)  # columns c and c + 1 not both at one level
            obstacles = [(s.c0, s.c1) for s in spans if s.kind != "flat"]
            for c0, c1 in obstacles:
                changes[max(c0 - 1, 0) : c1] = True
            self.rough[i] = spread(changes, self.margin)
            np.cumsum(changes, out=self._changes_before[i, 1:])
            self.first_obstacle[i] = x_min + obstacles[0][0] * res if obstacles else np.inf
            if self.ahead is None:
                self.complete(i)
        self.generated += len(ids)

    def reach(self, xy: np.ndarray, which: np.ndarray | None = None) -> None:
        """Write the terrain of copy ``which[k]`` (default: k) around ``xy[k]`` (m), as far as
        `ahead`, where it is not yet."""
        if self.ahead is None:
            return
        which = self._terrains[: len(xy)] if which is None else which
        (nrow, ncol), ahead = self.padded.shape[1:], self.ahead
        cells = self._cells(xy) + self._reach_base  # (stop column, middle row) of `padded`
        have = self.written[which]
        short = np.minimum(cells[:, 0], ncol) > have[:, 0]
        short |= np.maximum(cells[:, 1] - ahead, 0) < have[:, 1]
        short |= np.minimum(cells[:, 1] + ahead + 1, nrow) > have[:, 2]
        for k in np.flatnonzero(short).tolist():
            col, row = cells[k].tolist()
            self._extend(int(which[k]), min(col, ncol), max(row - ahead, 0), row + ahead + 1)

    def level(self, low: np.ndarray, high: np.ndarray, which: np.ndarray) -> np.ndarray:
        """Bool, shaped as ``low``: whether planned terrain ``which[k]`` (the last axis) is
        level at z = 0 for every x in [low[..., k], high[..., k]] (m), beyond its ends included
        (flat there)."""
        layout, last = self.layout, self.layout.ncol - 1
        cols = np.stack([low, high])
        cols -= layout.x_min
        cols *= 1.0 / layout.resolution
        np.minimum(np.maximum(cols, 0.0, out=cols), last, out=cols)
        strips = cols.astype(np.intp)  # the strip between columns c and c + 1 under each end
        np.minimum(strips[1] + 1, last, out=strips[1])
        counts = self._changes_before
        return counts[which, strips[1]] == counts[which, strips[0]]

    def ground(
        self, xy: np.ndarray, which: np.ndarray | None = None, floored: bool = False
    ) -> np.ndarray:
        self.reach(xy, which)
        return super().ground(xy, which, floored)

    def top(self, xy: np.ndarray, half: float, which: np.ndarray | None = None) -> np.ndarray:
        self.reach(xy, which)  # `ahead` is far more than an object's half size
        return super().top(xy, half, which)

    def complete(self, i: int) -> None:
        """Write the rest of copy ``i``'s terrain (to show or check all of it)."""
        self._extend(i, self.padded.shape[2], 0, self.padded.shape[1])

    def hfield_heights(self, i: int) -> np.ndarray:
        """Copy ``i``'s whole terrain as its heightfield holds it (in [0, 1] of the maximum
        height), without the padding; the rest of it is written first (`complete`)."""
        self.complete(i)
        m, (nrow, ncol) = self.margin, self.config.grid_shape
        return self._hfields[i][m : m + nrow, m : m + ncol]

    @property
    def heights(self) -> np.ndarray:
        for i in range(len(self.padded)):
            self.complete(i)
        return super().heights

    def _extend(self, i: int, stop: int, low: int, high: int) -> None:
        """Grow copy ``i``'s written rectangle to columns [0, stop) and rows [low, high) of
        `padded` (and `STRETCH` further), writing what it did not hold."""
        (nrow, ncol), stretch = self.padded.shape[1:], self._stretch
        old_stop, old_low, old_high = self.written[i].tolist()
        new_stop = min(stop + stretch, ncol) if stop > old_stop else old_stop
        new_low = max(low - stretch, 0) if low < old_low else old_low
        new_high = min(high + stretch, nrow) if min(high, nrow) > old_high else old_high
        if old_stop:  # more rows beside the columns written
            if new_low < old_low:
                self._render(i, (new_low, old_low), (0, old_stop))
            if new_high > old_high:
                self._render(i, (old_high, new_high), (0, old_stop))
        if new_stop > old_stop:
            self._render(i, (new_low, new_high), (old_stop, new_stop))
        self.written[i] = (new_stop, new_low, new_high)

    def _render(self, i: int, rows: tuple[int, int], cols: tuple[int, int]) -> None:
        """Write a rectangle of copy ``i``'s planned terrain, in the stack and its heightfield."""
        render(self.plans[i], self.padded[i], rows, cols, self.margin)
        block = (slice(*rows), slice(*cols))
        np.multiply(self.padded[i][block], self._normalise, out=self._hfields[i][block])
