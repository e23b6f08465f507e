"""`derl study` (appendix D): the stages as the coordinator's state plans them (retrain every
selected body, then test each world's best by mean on every task at every budget), its settings
checked, and end to end: runs of two worlds (two seeds of one), a study of them interrupted and
resumed by real coordinator and evaluator processes, and `derl report` drawing Fig. 4 from it."""

from __future__ import annotations

import csv
import json
import subprocess
from pathlib import Path

import pytest
import yaml
from body_variants import variants
from nodes_fixtures import (
    HandBirth,
    Processes,
    derl_argv,
    free_port,
    journaled,
    write_hand_run,
    write_profile,
)

from derl.analysis import RetrainJob, RetrainPlan
from derl.analysis.study import STUDY_PROFILES, StudyConfig, load_study_profile
from derl.messages import Curve, EvalJob, EvalResult, JobFailed
from derl.nodes.coordinator.study.files import SETUP_FILE, StudySetup, read_plan, read_setup
from derl.nodes.coordinator.study.state import StudyState
from derl.nodes.testing.waiting import wait_until
from derl.rl import PPOConfig
from derl.unimal import Genome, body_hash

CONFIG = StudyConfig(
    per_lineage=2,
    seeds=2,
    keep=2,
    top=1,
    test_tasks=("patrol",),
    test_seeds=1,
    budgets=(4096, 2048),
    num_envs=16,
    max_attempts=2,
)


def _plan(genome: Genome, bodies=(("r1", "a1", 90.0, "ft", 0), ("r2", "b1", 10.0, "ft", 1),
                                   ("r3", "c1", 5.0, "vt", 2))) -> RetrainPlan:  # fmt: skip
    """Retraining jobs of (run, agent, evolution fitness, world, body) with seeds 7 and 8, body k
    being variant k of `genome`; by default, two runs' bodies in ft, a1 (evolution fitness 90)
    and b1 (10), and c1 in vt."""
    genomes = variants(genome, 1 + max(body[-1] for body in bodies))
    jobs = tuple(
        RetrainJob(
            run=run,
            agent=agent,
            lineage="i0",
            fitness=fitness,
            task=world,
            steps=4096,
            seed=seed,
            genome=genomes[k],
        )
        for run, agent, fitness, world, k in bodies
        for seed in (7, 8)
    )
    return RetrainPlan(per_lineage=2, seeds=(7, 8), jobs=jobs)


def _answer(state: StudyState, key: tuple[str, str, int, int], reward: float, n: int) -> list:
    """The journal's messages for one evaluation done: its job, then its result."""
    genome, ppo = state.evaluation_order(key)
    agent, task, seed, steps = key
    job = EvalJob(run="s", job=f"e{n}", agent=agent, node="w", genome=genome, task=task, ppo=ppo,
                  lease_s=30.0)  # fmt: skip
    result = EvalResult(run="s", agent=agent, task=task, seed=seed, steps=steps, reward=reward,
                        cost_of_work=1.0, curve=Curve(), node="w", job=f"e{n}")  # fmt: skip
    return [job, result]


def test_the_tests_wait_for_every_retraining_and_take_the_best_by_mean(quadruped: Genome) -> None:
    state = StudyState(CONFIG, _plan(quadruped))
    journal: list = []
    means = {"r1.a1": (1.0, 3.0), "r2.b1": (20.0, 30.0), "r3.c1": (4.0, 6.0)}
    retraining = list(state.retrainings)
    assert [k[1:] for k in retraining[:2]] == [("ft", 7, 4096), ("ft", 8, 4096)]
    for n, key in enumerate(retraining):
        assert state.next_evaluation() in retraining  # no test before the last retraining
        reward = means[key[0]][key[2] - 7]
        for msg in _answer(state, key, reward, n):
            journal.append(msg)
            state.apply(msg)
    # b1: lowest evolution fitness, best mean (25 > 2): the one ft body tested
    assert state.tested == {"ft": [("r2.b1", 25.0)], "vt": [("r3.c1", 5.0)]}
    assert state.kept()["ft"] == [("r2.b1", 25.0), ("r1.a1", 2.0)]
    tests = [key for key in state.planned if key not in retraining]
    assert tests == [("r2.b1", "patrol", 0, 4096), ("r2.b1", "patrol", 0, 2048),
                     ("r3.c1", "patrol", 0, 4096), ("r3.c1", "patrol", 0, 2048)]  # fmt: skip
    assert state.eval_target == len(retraining) + 4 and not state.finished
    assert state.evaluation_order(tests[1])[1].total_steps == 2048
    restarted = StudyState(CONFIG, _plan(quadruped))  # a restart replays the journal
    for msg in journal:
        restarted.apply(msg)
    assert list(restarted.planned) == list(state.planned)
    assert restarted.next_evaluation() == tests[0]
    for n, key in enumerate(tests[:3]):
        for msg in _answer(state, key, 1.0, 100 + n):
            state.apply(msg)
    genome, ppo = state.evaluation_order(tests[3])
    for attempt in range(CONFIG.max_attempts):  # the last one fails: given up, not forever
        state.apply(EvalJob(run="s", job=f"f{attempt}", agent="r3.c1", node="w", genome=genome,
                            task="patrol", ppo=ppo, lease_s=30.0))  # fmt: skip
        state.apply(JobFailed(run="s", job=f"f{attempt}", node="w", agent="r3.c1", error="x"))
    assert state.eval_given_up == {tests[3]} and state.finished


def test_the_kept_hold_each_body_once_ranked_on_every_seed(quadruped: Genome) -> None:
    """An old plan selected body 0 twice (r1.a1, and r2.b1 of another run) and its retrainings
    are the same: it is kept and tested once. a3 has 1 of its 2 retrainings (the other given up):
    its 99 would rank first, it is not ranked."""
    bodies = (("r1", "a1", 50.0, "ft", 0), ("r2", "b1", 50.0, "ft", 0),
              ("r1", "a2", 40.0, "ft", 1), ("r1", "a3", 30.0, "ft", 2))  # fmt: skip
    config = CONFIG.model_copy(update={"top": 2, "keep": 3})
    state = StudyState(config, _plan(quadruped, bodies))
    rewards = {"r1.a1": (20.0, 30.0), "r2.b1": (20.0, 30.0), "r1.a2": (10.0, 10.0),
               "r1.a3": (99.0, None)}  # fmt: skip
    for n, key in enumerate(state.retrainings):
        reward = rewards[key[0]][key[2] - 7]
        if reward is None:  # given up
            genome, ppo = state.evaluation_order(key)
            for attempt in range(config.max_attempts):
                state.apply(EvalJob(run="s", job=f"f{attempt}", agent=key[0], node="w",
                                    genome=genome, task=key[1], ppo=ppo, lease_s=30.0))  # fmt: skip
                state.apply(JobFailed(run="s", job=f"f{attempt}", node="w", agent=key[0],
                                      error="x"))  # fmt: skip
            continue
        for msg in _answer(state, key, reward, n):
            state.apply(msg)
    assert state.kept() == {"ft": [("r1.a1", 25.0), ("r1.a2", 10.0)]}  # was a3, a1, b1
    assert state.next_evaluation()[0] == "r1.a1"  # the test stage starts
    assert state.tested == {"ft": [("r1.a1", 25.0), ("r1.a2", 10.0)]}  # was a3 and a1
    tests = {key[0] for key in state.planned if key not in state.retrainings}
    assert tests == {"r1.a1", "r1.a2"}


def test_a_retraining_given_up_still_lets_the_tests_start(quadruped: Genome) -> None:
    state = StudyState(CONFIG, _plan(quadruped))
    first, *rest = state.retrainings
    genome, ppo = state.evaluation_order(first)
    for attempt in range(CONFIG.max_attempts):
        state.apply(EvalJob(run="s", job=f"f{attempt}", agent=first[0], node="w", genome=genome,
                            task=first[1], ppo=ppo, lease_s=30.0))  # fmt: skip
        state.apply(JobFailed(run="s", job=f"f{attempt}", node="w", agent=first[0], error="x"))
    for n, key in enumerate(rest):
        for msg in _answer(state, key, 1.0, n):
            state.apply(msg)
    assert set(state.tested) == {"ft", "vt"}


def test_study_settings_are_checked(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="top"):
        StudyConfig(keep=5, top=10)
    with pytest.raises(ValueError, match="unknown task"):
        StudyConfig(test_tasks=("swim",))
    with pytest.raises(ValueError, match="repeat"):
        StudyConfig(budgets=(1_000_000, 1_000_000))
    with pytest.raises(ValueError, match="PPO of"):
        StudyConfig(budgets=(100,))
    typo = tmp_path / "mine.yaml"
    typo.write_text(yaml.safe_dump({"profile": "smoke", "test_seed": 3}))
    with pytest.raises(ValueError, match="test_seed"):
        load_study_profile(str(typo))
    typo.write_text(yaml.safe_dump({"profile": "smoke", "test_seeds": 3}))
    mine = load_study_profile(str(typo))
    assert (mine.name, mine.test_seeds, mine.budgets) == (
        "mine",
        3,
        STUDY_PROFILES["smoke"].budgets,
    )
    paper = STUDY_PROFILES["paper"]
    assert (paper.per_lineage, paper.seeds, paper.keep, paper.top, paper.test_seeds) == (
        3, 5, 100, 10, 5)  # fmt: skip
    assert paper.budgets == (5_000_000, 1_000_000) and len(paper.test_tasks) == 8


def _derl(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(derl_argv(*args), capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stdout + done.stderr
    return done


@pytest.mark.slow
def test_a_study_of_two_worlds_from_runs_to_figure_4(tmp_path: Path, procs: Processes) -> None:
    """Runs of 2 worlds, FT's of 2 seeds (a world's selection pools its runs) -> the study,
    planned and started by a coordinator and evaluators as on a cluster, killed mid-way, resumed
    by `derl study` -> `derl report`'s Fig. 4. Its jobs' lease is 10 s, not smoke's 30: the
    resumed study takes back the jobs the killed evaluators held once it is over."""
    profile = write_profile(tmp_path / "tiny.yaml")
    runs = [tmp_path / name for name in ("ft-s1", "ft-s2", "vt-s1")]
    evolving = [  # side by side: most of a tiny run is starting and announcing its end
        procs.start(run.name, derl_argv("run", "--profile", str(profile), "--env", run.name[:2],
                                        "--seed", run.name[-1], "--run-dir", str(run),
                                        "--port", "0", "--workers", "1"))
        for run in runs
    ]  # fmt: skip
    assert [procs.finish(run, 300) for run in evolving] == [0] * len(runs)
    study, run, endpoint = tmp_path / "study", "s1", f"tcp/127.0.0.1:{free_port()}"
    # as on a cluster: the coordinator plans the study from the runs, evaluators connect
    coordinator = procs.start("coordinator", derl_argv(
        "coordinator", "--run", run, "--study", str(study), "--study-runs", *map(str, runs),
        "--profile", "smoke", "--set", "lease_s=10", "--listen", endpoint))  # fmt: skip
    for k in range(2):
        procs.start(f"evaluator-{k}", derl_argv("evaluator", "--run", run, "--connect", endpoint,
                                                "--name", f"e{k}"))  # fmt: skip
    wait_until(lambda: len(journaled(study, EvalResult)) >= 3, 120, "3 results")
    for name in ("coordinator", "evaluator-0", "evaluator-1"):
        procs.kill(name)
    done = {(r.agent, r.task, r.seed, r.steps) for r in journaled(study, EvalResult)}
    issued = len(journaled(study, EvalJob))
    plan = read_plan(study)
    # then on one host: `derl study` resumes it where it stopped
    resume = procs.start(
        "resume", derl_argv("study", "--study-dir", str(study), "--port", "0", "--workers", "1")
    )
    assert coordinator.returncode != 0 and procs.finish(resume, 300) == 0
    assert read_plan(study) == plan  # chosen once
    keys = [(r.agent, r.task, r.seed, r.steps) for r in journaled(study, EvalResult)]
    assert len(keys) == len(set(keys)), "a result journaled twice"
    again = [j for j in journaled(study, EvalJob)[issued:]
             if (j.agent, j.task, j.seed, j.steps) in done]  # fmt: skip
    assert not again, "work done before the stop was done again"
    smoke = STUDY_PROFILES["smoke"]
    retrained = [k for k in keys if k[1] in ("ft", "vt")]
    assert (
        len(retrained) == len(plan.jobs) == smoke.seeds * len({(j.run, j.agent) for j in plan.jobs})
    )
    assert {j.run for j in plan.jobs} == {r.name for r in runs}
    tests = [k for k in keys if k[1] not in ("ft", "vt")]
    per_world = smoke.top * len(smoke.test_tasks) * len(smoke.budgets) * smoke.test_seeds
    assert len(tests) == 2 * per_world and {k[3] for k in tests} == set(smoke.budgets)
    selection = json.loads((study / "selection.json").read_text())
    for world in ("ft", "vt"):
        kept = selection[world]["kept"]
        assert kept and len(kept) <= smoke.keep
        assert [k["mean_fitness"] for k in kept] == sorted((k["mean_fitness"] for k in kept),
                                                           reverse=True)  # fmt: skip
        tested = {f"{t['run']}.{t['agent']}" for t in selection[world]["tested"]}
        assert tested == {k[0] for k in tests if k[0].startswith(f"{world}-")}
    out = tmp_path / "report"
    _derl("report", str(study), "--out", str(out), "--gaits", "0", "--pictures", "0")
    rows = (out / "tests.csv").read_text().splitlines()
    assert "steps" in rows[0].split(",") and len(rows) == 1 + len(tests)
    assert (out / "tests.png").stat().st_size > 10_000


def test_a_study_saved_when_ppo_held_every_ppoconfig_field_reads_back(tmp_path: Path) -> None:
    """A `study.json` written before 2026-12-03 holds every `PPOConfig` field under the
    settings' `ppo`, each training's copies, budget and seed included, which no training used:
    it reads back as the study it was."""
    setup = StudySetup(config=STUDY_PROFILES["smoke"], runs=(tmp_path / "run",))
    saved = setup.model_dump(mode="json")
    saved["config"]["ppo"] = PPOConfig(num_envs=64, total_steps=10**7, seed=5).model_dump()
    (tmp_path / SETUP_FILE).write_text(json.dumps(saved))
    assert read_setup(tmp_path) == setup


@pytest.mark.slow
def test_a_study_selects_retrains_and_tests_each_body_once(
    tmp_path: Path, quadruped: Genome
) -> None:
    """Two FT runs: in ra, c1 (a sibling) and c2 (a child) repeat c0's body D; rb's founder j0 is
    D too. The top 2 of each surviving lineage, each body once: ra's c0 (D) and i2, rb's k0 and
    j1, j2 (its j0 is D, selected from ra). A real study retrains and tests them, none twice,
    and its report says what was counted once."""
    a, b, c, d, e, f, g = variants(quadruped, 7)
    write_hand_run(tmp_path / "ra", "ra", "ft", [
        HandBirth("i0", None, a, 10.0), HandBirth("i1", None, b, 20.0),
        HandBirth("i2", None, c, 30.0), HandBirth("c0", "i2", d, 50.0),
        HandBirth("c1", "i2", d, repeat_of="c0"), HandBirth("c2", "c0", d, repeat_of="c0"),
    ])  # fmt: skip
    write_hand_run(tmp_path / "rb", "rb", "ft", [
        HandBirth("j0", None, d, 60.0), HandBirth("j1", None, e, 5.0),
        HandBirth("j2", None, f, 6.0), HandBirth("k0", "j0", g, 70.0),
    ])  # fmt: skip
    profile = tmp_path / "study.yaml"
    profile.write_text(yaml.safe_dump({"profile": "smoke", "per_lineage": 2, "keep": 3, "top": 2,
                                       "test_tasks": ["patrol"], "budgets": [2048]}))  # fmt: skip
    study = tmp_path / "study"
    _derl("study", str(tmp_path / "ra"), str(tmp_path / "rb"), "--study-dir", str(study),
          "--profile", str(profile), "--workers", "2", "--port", "0", timeout=600)  # fmt: skip
    plan = read_plan(study)
    selected = list(dict.fromkeys((j.run, j.agent) for j in plan.jobs))
    assert selected == [("ra", "c0"), ("ra", "i2"), ("rb", "k0"), ("rb", "j1"), ("rb", "j2")]
    assert len({body_hash(j.genome) for j in plan.jobs}) == len(selected)  # D once, not 3 times
    results = journaled(study, EvalResult)
    genomes = {f"{j.run}.{j.agent}": body_hash(j.genome) for j in plan.jobs}
    trained = [(genomes[r.agent], r.task, r.seed, r.steps) for r in results]
    assert len(trained) == len(set(trained)) == 5 * 2 + 2  # each training of a body once
    selection = json.loads((study / "selection.json").read_text())["ft"]
    kept = [genomes[f"{k['run']}.{k['agent']}"] for k in selection["kept"]]
    tested = [genomes[f"{t['run']}.{t['agent']}"] for t in selection["tested"]]
    assert len(kept) == len(set(kept)) == 3 and len(tested) == len(set(tested)) == 2
    out = tmp_path / "report"
    printed = _derl("report", str(study), "--out", str(out), "--gaits", "0", "--pictures", "0")
    text = " ".join(printed.stdout.split())
    assert "ra: 6 births, 4 distinct bodies (2 repeats" in text
    assert "median fitness of the first 1 births 10, of the last 1 50" in text
    stats = json.loads((out / "stats.json").read_text())
    (world,) = stats["worlds"]
    assert (world["retrained_bodies"], world["shared_bodies"], world["top_agents"]) == (5, 1, 5)
    bodies = [row for row in csv.DictReader((out / "bodies.csv").open())]
    counted = [(r["run"], r["id"]) for r in bodies if r["counted"] == "True"]
    assert ("ra", "c1") not in counted and ("rb", "j0") not in counted and len(counted) == 7
