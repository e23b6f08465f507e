"""The machine-readable tables of a report: CSV files (one pydantic row model each) and
stats.json (run and world sizes, the top agents' rule, fig. 5d's numbers, thresholds,
correlations, Mann-Whitney tests, what was sampled).

bodies.csv      one row per birth: tree, fitness, energy, descriptors, stability, learning speed,
                the earlier body a repeat took its result from (repeat_of), the first birth of
                the same body in the run (same_body_as), whether it counts as a body (counted:
                the first birth of its body in the world)
lineages.csv    one row per lineage: founder, rank, births and distinct bodies, survival,
                beneficial mutations
series.csv      every run's own curves: figure series, run, x, statistic, n, censored, value, CI
world_series.csv  the curves the figures draw, each world's runs pooled (n counts every run's)
muller.csv      abundance and mean fitness of the top lineages after each number of births
correlations.csv  fig. 6: per world, top agents or all bodies, pooled (generation empty) or per
                generation: Pearson's r over measured values, Spearman's counting censored ones
tests.csv       one row per evaluation result (with its budget, steps); test_summary.csv medians
                and CIs per budget, world and task
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable
from pathlib import Path

from pydantic import BaseModel

from derl.analysis.compute import (
    Analysis,
    CorrelationRow,
    RunAnalysis,
    RunSummary,
    WorldAnalysis,
    WorldSummary,
)
from derl.analysis.config import AnalysisConfig
from derl.analysis.lineage import Lineage
from derl.analysis.records import Record
from derl.analysis.testsuite import TaskSummary, TestResult, WorldComparison


class BodyRow(Record):
    run: str
    id: str
    parent: str | None
    founder: str
    generation: int
    birth: int
    fitness: float
    cost_of_work: float
    energy: float
    mass: float
    mutation: str | None
    repeat_of: str | None
    same_body_as: str | None
    """The first birth of this body in the run, where it is a later one."""
    counted: bool
    """The first birth of its body in the world: it counts as that body."""
    beneficial: bool
    descendants: int
    length: float
    width: float
    height: float
    dof: int
    limbs: int
    coverage: float | None
    passively_stable: bool | None
    stability_ratio: float | None
    steps_to_criterion: float | None
    """None where never reached (criterion_censored) or without a learning curve."""
    criterion_censored: bool
    """Its curve never reached the criterion within its budget."""
    top_agent: bool


class Stats(Record):
    """stats.json: what the figures rest on and the tests of figs. 4 and 6."""

    config: AnalysisConfig
    runs: list[RunSummary]
    worlds: list[WorldSummary]
    correlations: list[CorrelationRow]
    mann_whitney: list[WorldComparison]
    tests_repeated: int
    """Evaluations left out as the same body's training again."""
    notes: list[str]


SERIES_STATISTICS = {
    "steps_to_criterion": "median (Kaplan-Meier)",
    "cost_of_work": "median (Kaplan-Meier)",
}
"""The statistic of each series that is not a mean (a share is the mean of 0s and 1s)."""


class SeriesRow(Record):
    series: str
    run: str
    x: float
    statistic: str
    n: int
    censored: int
    value: float | None
    low: float | None
    high: float | None


class WorldSeriesRow(Record):
    series: str
    world: str
    runs: int
    x: float
    statistic: str
    n: int
    censored: int
    value: float | None
    low: float | None
    high: float | None


class MullerRow(Record):
    run: str
    time: int
    founder: str
    abundance: float
    mean_fitness: float | None


def body_rows(result: RunAnalysis) -> list[BodyRow]:
    run, tree = result.run, result.tree
    top = set(result.top.tolist())
    speed = result.measures["steps_to_criterion"]
    return [
        BodyRow(
            run=run.name,
            id=body.id,
            parent=body.parent,
            founder=run.bodies[tree.founder[i]].id,
            generation=int(tree.generation[i]),
            birth=body.birth,
            fitness=body.fitness,
            cost_of_work=body.cost_of_work,
            energy=body.energy,
            mass=body.mass,
            mutation=body.mutation,
            repeat_of=body.repeat_of,
            same_body_as=None if run.distinct[i] else run.bodies[run.original[i]].id,
            counted=bool(result.counted[i]),
            beneficial=bool(result.beneficial[i]),
            descendants=int(tree.descendants[i]),
            steps_to_criterion=(
                None if speed.censored[i] or math.isnan(speed.values[i]) else float(speed.values[i])
            ),
            criterion_censored=bool(speed.censored[i]),
            top_agent=i in top,
            **result.morphology[i].model_dump(exclude={"mass"}),
        )
        for i, body in enumerate(run.bodies)
    ]


def series_rows(result: RunAnalysis) -> list[SeriesRow]:
    return [
        SeriesRow(
            series=name,
            run=result.run.name,
            statistic=SERIES_STATISTICS.get(name, "mean"),
            **p.model_dump(),
        )
        for name, points in result.series.items()
        for p in points
    ]


def world_series_rows(result: WorldAnalysis) -> list[WorldSeriesRow]:
    return [
        WorldSeriesRow(
            series=name,
            world=result.summary.world,
            runs=len(result.runs),
            statistic=SERIES_STATISTICS.get(name, "mean"),
            **p.model_dump(),
        )
        for name, points in result.series.items()
        for p in points
    ]


def muller_rows(result: RunAnalysis) -> list[MullerRow]:
    m = result.muller
    return [
        MullerRow(
            run=result.run.name,
            time=int(t),
            founder=founder,
            abundance=float(m.abundance[row, col]),
            mean_fitness=None if math.isnan(m.fitness[row, col]) else float(m.fitness[row, col]),
        )
        for row, t in enumerate(m.times)
        for col, founder in enumerate(m.founders)
    ]


def write_csv(path: Path, rows: Iterable[BaseModel], model: type[BaseModel]) -> Path:
    """Rows as CSV with a header of `model`'s fields (nested models flattened as a_b)."""
    flat = [_flatten(row.model_dump()) for row in rows]
    header = list(_flatten(_example(model)).keys()) if not flat else list(flat[0])
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, header)
        writer.writeheader()
        writer.writerows({k: "" if v is None else v for k, v in row.items()} for row in flat)
    return path


def _example(model: type[BaseModel]) -> dict:
    """Field names of `model` (nested models expanded) for the header of an empty table."""
    names: dict = {}
    for name, field in model.model_fields.items():
        annotation = field.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            names[name] = _example(annotation)
        else:
            names[name] = None
    return names


def _flatten(row: dict, prefix: str = "") -> dict:
    flat = {}
    for key, value in row.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}_"))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def write_tables(analysis: Analysis, out: Path, notes: list[str]) -> list[Path]:
    """Every table of the report in `out`; the paths written."""
    runs = analysis.runs
    written = [
        write_csv(out / "bodies.csv", (row for r in runs for row in body_rows(r)), BodyRow),
        write_csv(out / "lineages.csv", (row for r in runs for row in r.lineages), Lineage),
        write_csv(out / "series.csv", (row for r in runs for row in series_rows(r)), SeriesRow),
        write_csv(
            out / "world_series.csv",
            (row for w in analysis.worlds for row in world_series_rows(w)),
            WorldSeriesRow,
        ),
        write_csv(out / "muller.csv", (row for r in runs for row in muller_rows(r)), MullerRow),
        write_csv(out / "correlations.csv", analysis.correlations, CorrelationRow),
        write_csv(out / "tests.csv", analysis.tests, TestResult),
        write_csv(out / "test_summary.csv", analysis.test_summary, TaskSummary),
    ]
    stats = Stats(
        config=analysis.config,
        runs=[r.summary for r in runs],
        worlds=[w.summary for w in analysis.worlds],
        correlations=analysis.correlations,
        mann_whitney=analysis.comparisons,
        tests_repeated=analysis.tests_repeated,
        notes=notes,
    )
    path = out / "stats.json"
    path.write_text(stats.model_dump_json(indent=2) + "\n")  # NaN becomes null
    return [*written, path]
