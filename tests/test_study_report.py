"""`write_report` on a study's runs: a world's runs pooled as the paper pools its 3 runs an
environment (fig. 2a: n = 3 x 100), its top agents by mean retrained fitness (appendix D), the
test suite split by training budget (fig. 4b and c), and fig. 5d's numbers, all on hand-built
records whose answers are worked out by hand."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from body_variants import variants

from derl.analysis import (
    AnalysisConfig,
    Body,
    BootstrapConfig,
    Evaluation,
    Retraining,
    RunLog,
    write_report,
)
from derl.analysis.testsuite import TestResult, budgets, results, tasks_and_worlds
from derl.unimal import Genome

STEPS = (100, 200, 300, 400, 500)
FAST = dict(
    time_points=3,
    stability_sample=1,
    pictures=0,
    gaits=0,
    bootstrap=BootstrapConfig(n_resamples=200),
)


def body(genome: Genome, id: str, birth: int, fitness: float, parent: str | None = None, curve=()):
    """A body whose learning curve (at STEPS) is `curve`, or climbs linearly to its fitness."""
    returns = curve or tuple(fitness * (k + 1) / len(STEPS) for k in range(len(STEPS)))
    return Body(
        id=id,
        parent=parent,
        birth=birth,
        fitness=fitness,
        curve_steps=STEPS,
        curve_returns=returns,
        cost_of_work=1.0 + birth % 3,
        energy=10.0,
        mass=5.0,
        mutation=None if parent is None else "density",
        genome=genome,
    )


def chain_run(
    genome: Genome, name: str, fitness: list[float], children: list[float], first=0, **records
):
    """Founders with `fitness`, then `children` each of the one born before it; the bodies are
    variants `first`, `first` + 1 ... of `genome` (runs of a world with the same `first` share
    their bodies)."""
    genomes = variants(genome, first + len(fitness) + len(children))[first:]
    founders = [body(genomes[k], f"{name}-i{k}", k, f) for k, f in enumerate(fitness)]
    line = []
    for k, f in enumerate(children):
        parent = line[-1].id if line else founders[-1].id
        line.append(body(genomes[len(founders) + k], f"{name}-c{k}", len(founders) + k, f, parent))
    return RunLog(name=name, bodies=(*founders, *line), **{"world": "ft", **records})


def table(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def test_fig2a_pools_the_top_100_of_3_runs(tmp_path: Path, quadruped: Genome) -> None:
    rng = np.random.default_rng(0)
    runs = [
        chain_run(quadruped, f"ft{k}", rng.uniform(0, 100, 100).tolist(), [150.0, 200.0], 102 * k)
        for k in range(3)
    ]
    written = write_report(runs, tmp_path, AnalysisConfig(top=100, **FAST))
    rows = [r for r in table(tmp_path / "world_series.csv") if r["world"] == "ft"]
    top = [r for r in rows if r["series"] == "fitness_top"]
    assert [int(r["n"]) for r in top] == [300] * len(top) and {r["runs"] for r in top} == {"3"}
    last = top[-1]  # after 102 births: each run's 100 latest, its founders 2-99 and children
    expected = np.mean([run.fitness[2:102] for run in runs])
    assert int(float(last["x"])) == 102 and float(last["value"]) == pytest.approx(expected)
    assert {int(r["n"]) for r in rows if r["series"] == "length"} == {300}  # fig. 3: 3 x P
    (world,) = json.loads((tmp_path / "stats.json").read_text())["worlds"]
    assert (world["top_of_population"], world["runs"]) == (300, ["ft0", "ft1", "ft2"])
    assert (world["top_rule"], world["top_agents"]) == ("evolution", 300)
    assert "n=300 (k=100/100/100)" in written.page.read_text()


def test_top_agents_are_the_best_by_mean_retrained_fitness(
    tmp_path: Path, quadruped: Genome
) -> None:
    def retrained(*agents: tuple[str, list[float]]) -> tuple[Retraining, ...]:
        return tuple(
            Retraining(agent=agent, seed=seed, steps=500, fitness=f)
            for agent, values in agents
            for seed, f in enumerate(values)
        )

    lucky = ("a-c1", [5.0, 10.0, 5.0, 10.0, 5.0])  # the fittest in evolution (900), 7 retrained
    a = chain_run(
        quadruped,
        "a",
        [10.0, 20.0, 30.0],
        [50.0, 900.0],
        retrained=retrained(lucky, ("a-c0", [40.0, 60.0, 50.0, 50.0, 50.0])),
    )
    b = chain_run(
        quadruped,
        "b",
        [10.0, 20.0, 30.0],
        [40.0, 45.0],
        5,
        retrained=retrained(("b-c1", [100.0, 80.0, 90.0, 90.0, 90.0]), ("b-c0", [8.0] * 5)),
    )
    written = write_report([a, b], tmp_path, AnalysisConfig(top=2, **FAST))
    top = [(r["run"], r["id"]) for r in table(tmp_path / "bodies.csv") if r["top_agent"] == "True"]
    assert sorted(top) == [("a", "a-c0"), ("b", "b-c1")]  # means 50 and 90; a-c1's is 7
    (world,) = json.loads((tmp_path / "stats.json").read_text())["worlds"]
    assert (world["top_rule"], world["top_agents"]) == ("retrained", 2)
    assert (world["retrained_bodies"], world["retrainings"]) == (4, 20)
    assert world["illustrative"]["last"] == "b-c1"  # generation 2, the deepest and best
    assert any("the 2 best of 4 retrained bodies" in note for note in written.notes)


def test_fig4_splits_the_tests_by_budget(tmp_path: Path, quadruped: Genome) -> None:
    def evaluations(offset: float) -> tuple[Evaluation, ...]:
        return tuple(
            Evaluation(
                agent="c0",
                task=task,
                seed=seed,
                steps=steps,
                reward=offset + steps / 1e6 + seed,
                cost_of_work=1.0,
            )
            for steps in (1_000_000, 5_000_000)
            for task in ("patrol", "incline")
            for seed in range(5)
        )

    ft = chain_run(quadruped, "ft", [1.0, 2.0, 3.0], [4.0], evaluations=evaluations(0.0))
    vt = chain_run(quadruped, "vt", [1.0, 2.0, 3.0], [4.0], world="vt")
    vt = vt.model_copy(update={"evaluations": evaluations(100.0)})
    written = write_report([ft, vt], tmp_path, AnalysisConfig(**FAST))
    tests = table(tmp_path / "tests.csv")
    assert len(tests) == 40 and {r["steps"] for r in tests} == {"1000000", "5000000"}
    summary = table(tmp_path / "test_summary.csv")
    assert len(summary) == 2 * 2 * 2  # budgets x tasks x worlds
    assert [r["steps"] for r in summary[::4]] == ["5000000", "1000000"]  # the largest first
    for row in summary:  # five seeds of one budget each, never the two budgets pooled
        offset = 0.0 if row["world"] == "ft" else 100.0
        assert int(row["reward_n"]) == 5
        assert float(row["reward_value"]) == pytest.approx(offset + int(row["steps"]) / 1e6 + 2)
    stats = json.loads((tmp_path / "stats.json").read_text())["mann_whitney"]
    assert len(stats) == 2 * 2 * 2  # budgets x tasks x metrics, FT against VT
    assert {c["steps"] for c in stats} == {1_000_000, 5_000_000}
    assert all(c["test"]["n_a"] == 5 for c in stats)
    assert "5,000,000 env steps: 20 results; 1,000,000 env steps: 20 results" in (
        written.page.read_text()
    )
    unknown = ft.model_copy(
        update={"evaluations": (Evaluation(agent="c0", task="x", seed=0, reward=1),)}
    )
    assert budgets(results([unknown, vt])[0]) == [5_000_000, 1_000_000, None]


def test_fig5d_numbers_of_a_lineage(tmp_path: Path, quadruped: Genome) -> None:
    """Founders 10, 20, 30: the criterion is 25. The lineage i2 -> c0 -> c1 -> c2 learns
    better and sooner each generation; the top 2 agents are c2 and c1."""
    curves = {
        "r-i2": (5.0, 10.0, 20.0, 25.0, 30.0),  # reaches 25 at 400
        "r-c0": (10.0, 25.0, 35.0, 40.0, 45.0),
        "r-c1": (20.0, 30.0, 45.0, 55.0, 60.0),  # 25 at 200, final x2
        "r-c2": (30.0, 60.0, 80.0, 85.0, 90.0),  # 25 at 100, final x3
    }
    run = chain_run(quadruped, "r", [10.0, 20.0, 30.0], [45.0, 60.0, 90.0])
    bodies = tuple(
        b.model_copy(update={"curve_returns": curves.get(b.id, b.curve_returns)})
        for b in run.bodies
    )
    run = run.model_copy(update={"bodies": bodies})
    written = write_report([run], tmp_path, AnalysisConfig(top=2, **FAST))
    (world,) = json.loads((tmp_path / "stats.json").read_text())["worlds"]
    one = world["illustrative"]
    assert (one["first"], one["last"], one["generations"]) == ("r-i2", "r-c2", 3)
    assert (one["first_return"], one["last_return"], one["return_ratio"]) == (30.0, 90.0, 3.0)
    assert (one["first_steps"], one["last_steps"], one["speedup"]) == (400, 100, 4.0)
    assert one["last_steps_to_first_return"] == 100
    assert world["gains"] == dict(
        agents=2, return_ratio=2.5, speedup=3.0, first_steps=400, last_steps=150, speedup_defined=2
    )
    page = written.page.read_text()
    assert "final return 30 to 90 (x3), env steps to the criterion 400 to 100 (x4 sooner)" in page
    assert "median speed-up x3 (n=2" in page


def test_every_fig4_panel_orders_tasks_and_worlds_as_the_paper() -> None:
    """Whatever order the results came in (here each budget's differs, VT first), every panel
    and table lists the tasks as fig. 4 does and the worlds FT, VT, MVT."""
    rows = [
        TestResult(
            run="r",
            world=world,
            agent="a",
            task=task,
            seed=0,
            steps=steps,
            reward=1.0,
            cost_of_work=1.0,
        )
        for steps, tasks in ((2048, ("obstacle", "patrol")), (4096, ("patrol", "obstacle")))
        for world in ("vt", "ft")
        for task in tasks
    ]
    for steps in (2048, 4096):
        group = [r for r in rows if r.steps == steps]
        assert tasks_and_worlds(group) == (["patrol", "obstacle"], ["ft", "vt"])


def test_fig4_draws_a_cost_of_work_whose_median_or_limits_are_unknown(
    tmp_path: Path, quadruped: Genome
) -> None:
    """A body that never reached a task's goal (reward <= 0) has no cost of work: a censored
    value. Where half or more of a task's results are censored, the median is unknown; where a
    few are, a limit may be: the report draws them (it failed on an FT demo run of 2 bodies)."""
    reached = {"patrol": (1, 2), "incline": (0, 1, 2, 3)}  # the seeds whose body reached the goal
    evaluations = tuple(
        Evaluation(agent="c0", task=task, seed=seed, steps=1_000_000,
                   reward=1.0 + seed if seed in done else -1.0,
                   cost_of_work=0.5 + seed if seed in done else float("nan"))
        for task, done in reached.items()
        for seed in range(5)
    )  # fmt: skip
    run = chain_run(quadruped, "ft", [1.0, 2.0, 3.0], [4.0], evaluations=evaluations)
    write_report([run], tmp_path, AnalysisConfig(**FAST))
    summary = {row["task"]: row for row in table(tmp_path / "test_summary.csv")}
    assert summary["patrol"]["cost_of_work_value"] == ""  # 3 of 5 censored: unknown
    assert float(summary["incline"]["cost_of_work_value"]) == pytest.approx(2.5)
    assert (tmp_path / "tests.png").stat().st_size > 10_000
