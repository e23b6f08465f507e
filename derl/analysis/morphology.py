"""Morphological descriptors of every body and their population means over time (fig. 3, 5b),
of one run or of a world's runs pooled.

Length, width, height (bounding box at rest), DoF and limb count are cheap and measured for every
body; mass is the one lifetime learning reported. Coverage and passive stability come from
`derl.unimal.describe`, which simulates 400 uncontrolled steps (tens of ms a body): it runs on
every body of a small run and on an evenly spaced sample in birth order (every k-th body) of a
big one, in `processes` worker processes, once per body: a repeat has its original's values
(also where only its original was in the sample).
"""

from __future__ import annotations

import logging
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from derl.analysis.lineage import window
from derl.analysis.records import Record, RunLog
from derl.analysis.statistics import BootstrapConfig, Point, point
from derl.unimal import Descriptors, Genome, describe
from derl.unimal.geometry import bounding_box, layout

log = logging.getLogger("derl.analysis")

DESCRIPTORS = ("length", "width", "height", "coverage", "mass", "dof")
"""Fig. 3's panels, in order."""


class Morphology(Record):
    """What a body looks like; the physics-based fields are None when it was not simulated."""

    length: float
    width: float
    height: float
    dof: int
    limbs: int
    mass: float
    coverage: float | None = None
    passively_stable: bool | None = None
    stability_ratio: float | None = None


def sample(n: int, size: int) -> np.ndarray:
    """Indices of `size` bodies evenly spread over a birth order of `n` (all when n <= size)."""
    if n <= size:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, size).round().astype(int))


def measure(run: RunLog, sample_size: int, processes: int = 1) -> list[Morphology]:
    """Every body's descriptors; coverage and stability for `sample(...)` of them."""
    missing = [body.id for body in run.bodies if body.genome is None]
    if missing:
        raise ValueError(f"{run.name}: no genome for {', '.join(missing[:5])}")
    simulated = np.unique(run.original[sample(len(run.bodies), sample_size)]).tolist()
    log.info("%s: simulating the passive stability of %d bodies", run.name, len(simulated))
    genomes = [run.bodies[i].genome for i in simulated]
    physics = dict(zip(simulated, _describe_all(genomes, processes), strict=True))
    rows = []
    for i, body in enumerate(run.bodies):
        assert body.genome is not None  # (`missing` above)
        low, high = bounding_box(layout(body.genome))
        length, width, height = (high - low).tolist()
        described = physics.get(int(run.original[i]))
        rows.append(
            Morphology(
                length=length,
                width=width,
                height=height,
                dof=body.genome.dof,
                limbs=body.genome.num_limbs,
                mass=body.mass,
                coverage=None if described is None else described.coverage,
                passively_stable=None if described is None else described.passively_stable,
                stability_ratio=None if described is None else described.stability_ratio,
            )
        )
    return rows


def _describe_all(genomes: list[Genome], processes: int) -> list[Descriptors]:
    if processes <= 1 or len(genomes) < 2 * processes:
        return [describe(genome) for genome in genomes]
    with ProcessPoolExecutor(processes) as pool:
        return list(pool.map(describe, genomes, chunksize=max(1, len(genomes) // (4 * processes))))


def column(rows: list[Morphology], name: str) -> np.ndarray:
    """One descriptor of every body as floats (NaN where not measured)."""
    return np.array([np.nan if (v := getattr(r, name)) is None else v for r in rows], dtype=float)


def over_time(
    parts: list[tuple[np.ndarray, int]], times: np.ndarray, config: BootstrapConfig
) -> list[Point]:
    """Population mean (with CI) of per-body values after each number of births in `times`,
    the populations of every part (values, population: one run's) pooled."""
    return [
        point(int(t), np.concatenate([v[window(int(t), p)] for v, p in parts]), config)
        for t in times
    ]
