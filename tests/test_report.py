"""`derl report` and `derl study --plan-only` on journals: a hand-written one (the fold into
records, every file of a report), and a real smoke run made by `derl run` (slow)."""

from __future__ import annotations

import argparse
import csv
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from body_variants import variants
from nodes_fixtures import SMOKE_RUN, FinishedRun

from derl.analysis import RetrainPlan
from derl.evolution import breed
from derl.messages import Ack, Birth, Curve, EvalResult, FitnessReport, Tournament, TrainJob
from derl.nodes.cli.main import main
from derl.nodes.cli.report import _thresholds
from derl.nodes.journal.history import load_runs
from derl.nodes.journal.history import run_log as load_run
from derl.nodes.journal.segments import Journal, segments
from derl.rl import PPOConfig
from derl.unimal import Genome

FIGURES = (
    "fitness.png",
    "lineages.png",
    "phylogeny.png",
    "muller.png",
    "morphology.png",
    "baldwin.png",
    "curves.png",
    "energy.png",
    "tests.png",
    "bodies.png",
)
TABLES = (
    "bodies.csv",
    "lineages.csv",
    "series.csv",
    "muller.csv",
    "tests.csv",
    "test_summary.csv",
    "stats.json",
)


def _job(
    child: str, genome: Genome, parent: str | None, attempt: int = 1, mutation: str | None = None
) -> TrainJob:
    return TrainJob(
        run="hand",
        job=f"{child}.{attempt}",
        agent=child,
        node="t0",
        genome=genome,
        task="vt",
        ppo=PPOConfig(total_steps=300, num_envs=1, rollout_steps=100, minibatch_size=100),
        parent=parent,
        mutation=mutation,
        lease_s=30,
    )


def _report(
    child: str,
    fitness: float,
    curve: tuple[float, ...],
    genome: Genome,
    attempt: int = 1,
):
    return FitnessReport(
        run="hand",
        agent=child,
        job=f"{child}.{attempt}",
        node="t0",
        genome=genome,
        fitness=fitness,
        fitness_source="window",
        fitness_episodes=3,
        curve=Curve(env_steps=(100, 200, 300), returns=curve),
        energy=50.0,
        cost_of_work=2.0,
        mass=12.0,
        episodes=9,
        env_steps=300,
        wall_s=1.0,
        steps_per_s=300.0,
        checkpoint=b"",
    )


def _birth(
    report: FitnessReport, parent: str | None, birth: int, generation: int, mutation: str | None
) -> Birth:
    """The coordinator's Birth of an accepted `report` (of a job made by `mutation`)."""
    return Birth(
        run=report.run, agent=report.agent, parent=parent, job=report.job, node=report.node,
        birth=birth, generation=generation, fitness=report.fitness,
        cost_of_work=report.cost_of_work, energy=report.energy, mass=report.mass,
        mutation=mutation, genome=report.genome,
    )  # fmt: skip


def write_journal(run_dir: Path, genome: Genome) -> None:
    """P = 3 founders i0..i2, then c0 (of i2, its job reassigned once) and c1 (of c0); a repeated
    fitness report and a repeated evaluation result, as a journal may hold after restarts."""
    founders = [*variants(genome, 2), genome]  # three bodies
    c0_body = breed(founders[2], 7)[0]
    c1_body = c0_body  # a gear mutation that drew the gears c0 had: the same body
    with Journal(run_dir) as journal:
        for k, fitness in enumerate((10.0, 20.0, 30.0)):
            journal.write(_job(f"i{k}", founders[k], None))
            report = _report(f"i{k}", fitness, (fitness / 2, fitness, fitness), founders[k])
            journal.write(report)
            journal.write(_birth(report, None, k, 0, None))
            journal.write(
                Ack(run="hand", of="FitnessReport", job=f"i{k}.1", agent=f"i{k}", node="t0")
            )
        journal.write(_report("i1", 99.0, (1.0, 2.0, 3.0), founders[1]))  # repeated: 1st counts
        made = {"c0": "grow_limb", "c1": "gear"}
        for child, parent, body, k in (("c0", "i2", c0_body, 0), ("c1", "c0", c1_body, 1)):
            journal.write(
                Tournament(
                    run="hand",
                    agent=child,
                    contestants=(parent,),
                    fitness=(1.0,),
                    parent=parent,
                    mutation_seed=7,
                    iteration=k,
                )
            )
            journal.write(_job(child, body, parent, mutation=made[child]))
        journal.write(_job("c0", c0_body, "i2", attempt=2, mutation=made["c0"]))
        for report, parent, k in (
            (_report("c0", 150.0, (20.0, 40.0, 150.0), c0_body, 2), "i2", 3),
            (_report("c1", 400.0, (30.0, 200.0, 400.0), c1_body), "c0", 4),
        ):
            journal.write(report)
            journal.write(_birth(report, parent, k, k - 2, made[report.agent]))
        for task, seed, reward in (("patrol", 0, 5.0), ("patrol", 1, 7.0), ("incline", 0, 3.0)):
            result = EvalResult(
                run="hand",
                agent="c1",
                task=task,
                seed=seed,
                steps=1000,
                reward=reward,
                cost_of_work=1.5,
                curve=Curve(),
                node="e0",
                job=f"e-{task}-{seed}",
            )
            journal.write(result)
            if seed == 1:
                journal.write(result.model_copy(update={"reward": 0.0}))


def test_the_journal_folds_into_records(tmp_path: Path, quadruped: Genome) -> None:
    write_journal(tmp_path, quadruped)
    run = load_run(tmp_path)
    assert (run.name, run.world, run.train_steps, run.training_seed) == ("hand", "vt", 300, 1409)
    assert [b.id for b in run.bodies] == ["i0", "i1", "i2", "c0", "c1"]
    assert [b.parent for b in run.bodies] == [None, None, None, "i2", "c0"]
    assert [b.mutation for b in run.bodies] == [None, None, None, "grow_limb", "gear"]
    assert run.bodies[1].fitness == 20.0
    assert run.bodies[4].curve_returns == (30.0, 200.0, 400.0)
    assert run.bodies[3].genome == breed(quadruped, 7)[0] != quadruped  # the bodies bred
    assert run.bodies[2].genome == quadruped != run.bodies[0].genome and run.population == 3
    assert [(e.task, e.seed, e.reward) for e in run.evaluations] == [
        ("patrol", 0, 5.0),
        ("patrol", 1, 7.0),
        ("incline", 0, 3.0),
    ]
    assert load_run(segments(tmp_path)[0]) == run  # one MCAP file reads the same
    twice = load_runs([tmp_path, tmp_path])
    assert [r.name for r in twice] == ["hand", "hand-2"]


def test_beneficial_flag() -> None:
    assert _thresholds("300") == {"*": 300.0}
    assert _thresholds("FT=300, vt=50") == {"ft": 300.0, "vt": 50.0}
    with pytest.raises(argparse.ArgumentTypeError):
        _thresholds("ft=lots")


def _table(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _check_report(out: Path) -> dict:
    """Every figure and table written and on the page, and the tables behind the figures (the
    population's fitness over time, lineages, Muller abundances, test summaries) consistent with
    the bodies and test results the report lists; the stats."""
    for name in FIGURES:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
        assert (out / name).stat().st_size > 5_000, name
    page = (out / "index.html").read_text()
    for name in FIGURES + TABLES:
        assert f'"{name}"' in page, name
    stats = json.loads((out / "stats.json").read_text())
    (summary,) = stats["runs"]
    bodies = _table(out / "bodies.csv")
    assert len(bodies) == summary["bodies"]
    assert [int(b["birth"]) for b in bodies] == list(range(len(bodies)))
    by_id = {b["id"]: b for b in bodies}
    for b in bodies:  # a child is one generation after its parent, in its parent's lineage
        parent = by_id.get(b["parent"])
        assert int(b["generation"]) == (int(parent["generation"]) + 1 if parent else 0), b
        assert b["founder"] == (parent["founder"] if parent else b["id"]), b
    fitness = [float(b["fitness"]) for b in bodies]
    founders = [b["founder"] for b in bodies]
    size, top = summary["population"], summary["top_of_population"]
    final = set(founders[-size:])

    def population(t: int) -> range:  # the P latest born after t births
        return range(max(0, t - size), t)

    times = sorted({int(float(r["x"])) for r in _table(out / "series.csv")
                    if r["series"] == "fitness_top"})  # fmt: skip
    assert times[0] == min(size, len(bodies)) and times[-1] == len(bodies), times
    for row in _table(out / "series.csv"):
        assert list(row) == ["series", "run", "x", "statistic", "n", "censored", "value", "low",
                             "high"]  # fmt: skip
        if row["low"] and row["high"]:
            assert float(row["low"]) <= float(row["value"]) <= float(row["high"]), row
        if row["series"] == "fitness_top":  # the mean of the population's k fittest
            fittest = sorted(fitness[i] for i in population(int(float(row["x"]))))[-top:]
            assert float(row["value"]) == pytest.approx(sum(fittest) / top), row
            assert row["low"] == "" or float(row["low"]) >= min(fittest) - 1e-9, row
    lineages = _table(out / "lineages.csv")
    assert sorted(r["founder"] for r in lineages) == sorted(set(founders))
    for row in lineages:
        mine = [i for i, f in enumerate(founders) if f == row["founder"]]
        members = sum(founders[i] == row["founder"] for i in population(len(bodies)))
        assert int(row["bodies"]) == len(mine) and int(row["final_members"]) == members, row
        assert (row["surviving"] == "True") == (row["founder"] in final), row
        assert float(row["best_fitness"]) == max(fitness[i] for i in mine), row
    muller = _table(out / "muller.csv")
    assert {r["founder"] for r in muller} == final  # (at most muller_lineages of them)
    assert {int(r["time"]) for r in muller} == set(times)
    for row in muller:  # a lineage's share of the population, and its mean fitness in it
        span = population(int(row["time"]))
        mine = [fitness[i] for i in span if founders[i] == row["founder"]]
        assert float(row["abundance"]) == pytest.approx(len(mine) / len(span)), row
        if mine:
            assert float(row["mean_fitness"]) == pytest.approx(sum(mine) / len(mine)), row
    tests = _table(out / "tests.csv")
    summaries = _table(out / "test_summary.csv")
    assert {r["task"] for r in summaries} == {r["task"] for r in tests}
    for row in summaries:
        rewards = [float(r["reward"]) for r in tests if r["task"] == row["task"]]
        assert int(row["reward_n"]) == len(rewards), row
        assert float(row["reward_value"]) == pytest.approx(sum(rewards) / len(rewards)), row
    return stats


def test_report_of_a_journal(tmp_path: Path, quadruped: Genome) -> None:
    write_journal(tmp_path / "run", quadruped)
    out = tmp_path / "report"
    assert (
        main(
            [
                "report",
                str(tmp_path / "run"),
                "--out",
                str(out),
                "--beneficial",
                "vt=120",
                "--pictures",
                "0",
                "--processes",
                "1",
            ]
        )
        == 0
    )
    stats = _check_report(out)
    (run,) = stats["runs"]
    assert (run["bodies"], run["population"], run["generations"]) == (5, 3, 3)
    assert (run["beneficial_threshold"], run["beneficial_mutations"]) == (120.0, 2)
    assert run["criterion"] == 25.0  # 75th percentile of 10, 20, 30
    fingerprint = load_runs([tmp_path / "run"])[0].fingerprint
    assert fingerprint and run["fingerprint"] == fingerprint
    assert (run["audited"], run["quarantined"]) == (0, [])
    page = (out / "index.html").read_text()
    assert f"<td>{fingerprint}</td>" in page and "quarantined trainers" in page
    rows = (out / "bodies.csv").read_text().splitlines()
    assert len(rows) == 6 and rows[0].startswith("run,id,parent,founder,generation,birth")
    assert "hand,c1,c0,i2,2,4,400.0" in rows[5]
    assert len((out / "tests.csv").read_text().splitlines()) == 4


def test_a_run_given_twice_under_two_names_is_refused(
    tmp_path: Path, quadruped: Genome, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two runs with one fingerprint are one run's births: pooled, n would count them twice."""
    write_journal(tmp_path / "run", quadruped)
    shutil.copytree(tmp_path / "run", tmp_path / "copy")
    with pytest.raises(SystemExit) as refused:
        main(["report", str(tmp_path / "run"), str(tmp_path / "copy"), "--out", str(tmp_path)])
    assert refused.value.code == 1
    assert "hand and hand-2 are the same run (fingerprint " in capsys.readouterr().err


def test_study_plan_only_writes_the_retraining_jobs(tmp_path: Path, quadruped: Genome) -> None:
    write_journal(tmp_path / "run", quadruped)
    profile = tmp_path / "select.yaml"
    profile.write_text(yaml.safe_dump({"profile": "paper", "per_lineage": 2, "seeds": 3}))
    study = tmp_path / "study"
    argv = ["study", str(tmp_path / "run"), "--study-dir", str(study), "--plan-only"]
    assert main([*argv, "--profile", str(profile)]) == 0
    result = RetrainPlan.model_validate_json((study / "plan.json").read_text())
    # the final population (the last 3 born: i2, c0, c1) is one lineage, i2's; c1 is c0's body
    # (its gear mutation drew the gears c0 had): counted once, as c0
    assert [j.agent for j in result.jobs[::3]] == ["c0", "i2"]
    assert len(result.jobs) == 6 and 1409 not in result.seeds
    assert {(j.task, j.steps, j.lineage) for j in result.jobs} == {("vt", 300, "i2")}


def derl(*args: str) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(
        [sys.executable, "-m", "derl.nodes.cli", *args], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return result


@pytest.mark.slow
@SMOKE_RUN
def test_report_of_a_real_smoke_run(smoke_run: FinishedRun, tmp_path: Path) -> None:
    run_dir, ran = smoke_run
    printed_print = re.search(r"fingerprint\s+([0-9a-f]{16})", ran.stdout)
    assert printed_print is not None, ran.stdout
    fingerprint = printed_print.group(1)
    assert json.loads((run_dir / "summary.json").read_text())["fingerprint"] == fingerprint
    out = tmp_path / "report"  # its gaits aside: tests/test_replay.py films a run's
    printed = derl("report", str(run_dir), "--out", str(out), "--gaits", "0").stdout
    assert f"wrote {out / 'index.html'}" in printed.replace("\n", "")
    assert re.search(rf"fingerprint\s+{fingerprint}", printed), printed
    stats = _check_report(out)
    assert stats["runs"][0]["bodies"] == 8 and stats["runs"][0]["world"] == "ft"
    assert (out / "bodies.png").stat().st_size > 50_000  # real pictures, not the placeholder
    assert len((out / "tests.csv").read_text().splitlines()) > 1  # the evaluator's results
    study = tmp_path / "study"
    derl("study", str(run_dir), "--study-dir", str(study), "--profile", "paper", "--plan-only")
    result = RetrainPlan.model_validate_json((study / "plan.json").read_text())
    lineages = _table(out / "lineages.csv")  # each lineage's top 3, each body once
    surviving = [
        min(3, int(row["distinct_bodies"])) for row in lineages if row["surviving"] == "True"
    ]
    assert len(result.jobs) == 5 * sum(surviving) and len(result.seeds) == 5
