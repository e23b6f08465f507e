"""Plugins from a researcher's own package (examples/: a world with its own terrain and reward
term, a selection scheme, a mutation operator), installed for real and run like built-ins: found
by entry point or by ``module:name``, identified on every job, refused by a node that lacks them
(the run finishes on the others), with the fingerprint the same on 1 trainer and 3; the fitness
bound derived from the task's own terms; every bad plugin one line and an exit status."""

from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import yaml
from nodes_fixtures import (
    REPO,
    LocalRun,
    Processes,
    assert_born_once,
    derl_argv,
    free_port,
    journaled,
    run_id,
    write_profile,
)

import derl
from derl.envs import EnvConfig, make_task
from derl.envs.registry import TASK_REGISTRY
from derl.envs.rewards import RewardWeights
from derl.envs.task import Task
from derl.envs.worlds import ft
from derl.evolution import load_profile
from derl.evolution.evolution import tournament_draws
from derl.evolution.member import Member
from derl.evolution.selection import (
    SELECTION_REGISTRY,
    Draws,
    Selected,
    Selection,
    make_selection,
    select,
)
from derl.messages import Ack, EvalResult, JobFailed, MessageBase, Reject, TrainJob, WorkerReady
from derl.nodes.cli.main import main
from derl.nodes.coordinator.node import Coordinator, Liveliness
from derl.nodes.coordinator.run.rules import EvolutionRules
from derl.nodes.journal.history import load_history
from derl.nodes.testing.trainers import Recorder, fake_report
from derl.nodes.testing.waiting import wait_until
from derl.unimal import Genome, random_genome
from derl.unimal.mutations import OPERATOR_REGISTRY, OPERATORS, mutate

pytestmark = pytest.mark.xdist_group("plugins")  # one install of the examples

PACKAGES = ("derl-stairs", "derl-cheap-parents", "derl-stiffen")
PLUGIN_PROFILE = {
    "population": 4,  # smoke's 8 bodies: 4 initial ones and 4 children
    "in_flight": 2,
    "total": 8,
    "world": "stairs",
    "selection": "cheap_parents",
    "selection_options": {"penalty": 20.0},
    "mutations": {"stiffen": 2.0, "gear": 1.0, "dof": 1.0, "grow_limb": 1.0},
    "eval_top": 1,
    "eval_tasks": ["stairs"],
    "eval_steps": 2048,
    "train_steps": 4096,
}


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The three example packages installed (pip, as a user would) into a folder of their own:
    a process sees them where that folder is on its path, a node without it lacks them."""
    target = tmp_path_factory.mktemp("plugins")
    packages = [str(REPO / "examples" / name) for name in PACKAGES]
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
         "--target", str(target), *packages],
        check=True,
    )  # fmt: skip
    return target


@pytest.fixture
def plugins(installed: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.syspath_prepend(str(installed))
    return installed


# --- pieces a test names as module:name ----------------------------------------------------------


def heavy_ft() -> Task:
    """FT whose forward term weighs 3: its fitness can be 3 x FT's."""
    return ft(weights=RewardWeights(forward=3.0))


def raising_task() -> Task:
    raise RuntimeError("no terrain today")


def outsider() -> Selection:
    def select(pool: Sequence[Member], draws: Draws) -> Selected:
        stranger = Member("c99999", 1e9, None, 0)
        return Selected(stranger, (stranger,))

    return select


def junk_operator(genome: Genome, rng: np.random.Generator) -> object:
    return 42


def invalid_operator(genome: Genome, rng: np.random.Generator) -> tuple[Genome, str]:
    """Every child has a 0.2 m limb stuck in the head, which no body survives."""
    data = genome.model_dump()
    data["head_density"] = -1.0  # out of the design space: a ValidationError each time
    return Genome.model_validate(data), "broken"


# --- registries ----------------------------------------------------------------------------------


def test_installed_plugins_are_found_identified_and_registered_as_gym_ids(plugins: Path) -> None:
    stairs = TASK_REGISTRY.identity("stairs")
    assert stairs is not None
    assert (stairs.distribution, stairs.version, stairs.target) == (
        "derl-stairs", "0.1.0", "derl_stairs:stairs")  # fmt: skip
    assert len(stairs.source) == 64
    spec = TASK_REGISTRY.identity("derl_stairs:stairs")
    assert spec is not None and spec.target == stairs.target and spec.source == stairs.source
    assert SELECTION_REGISTRY.identity("cheap_parents").distribution == "derl-cheap-parents"  # type: ignore[union-attr]
    assert OPERATOR_REGISTRY.identity("stiffen").version == "0.1.0"  # type: ignore[union-attr]
    assert TASK_REGISTRY.identity("ft") is None  # a built-in
    derl.register_gym_envs()
    body = random_genome(np.random.default_rng(0))
    env = gymnasium.make("derl/Stairs-v0", genome=body)
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"proprioception", "heightmap"}
    _, reward, *_ = env.step(env.action_space.sample())
    assert np.isfinite(reward)
    env.close()


# --- the fitness bound, derived ------------------------------------------------------------------


def _answers(world: str, fitness: float, tmp_path: Path) -> MessageBase:
    """What a coordinator of a run in `world` answers a report of `fitness` (its job's body and a
    policy of it): an Ack or a Reject."""
    run, heard = "tbound", Recorder()
    config = load_profile("smoke", world=world).model_copy(update={"eval_top": 0, "eval_tasks": ()})
    coordinator = Coordinator(run, tmp_path, EvolutionRules(run, tmp_path, config), heard)
    try:
        coordinator.take(Liveliness("trainer", "w1", True))
        coordinator.take(WorkerReady(run=run, node="w1", role="trainer", host="h", pid=1))
        coordinator.settle()
        job = next(m for m in heard.messages if isinstance(m, TrainJob))
        coordinator.take(fake_report(run, job, fitness).model_copy(update={"env_steps": job.steps}))
        coordinator.settle()
        return next(m for m in heard.messages if isinstance(m, Ack | Reject))
    finally:
        coordinator.close()


@pytest.mark.parametrize(
    ("world", "scale"),
    [("tests.test_plugins:heavy_ft", 3.0), ("stairs", None)],
)
def test_a_changed_weight_or_a_new_term_moves_the_bound_with_no_other_edit(
    plugins: Path, tmp_path: Path, world: str, scale: float | None
) -> None:
    """FT with its forward weight tripled allows a fitness beyond plain FT's bound, and rejects
    one beyond three times it; the stairs' new term (climbing, with its own per-step bound)
    counts in its world's bound the same way."""
    task = make_task(world)
    bound = EnvConfig().fitness_bound(task)
    plain = EnvConfig().fitness_bound(make_task("ft" if scale else "vt"))
    if scale:
        assert bound == pytest.approx(scale * plain)
    honest = min(1.5 * plain, 0.9 * bound)
    assert honest > plain or scale is None
    assert isinstance(_answers(world, honest, tmp_path / "honest"), Ack)
    rejected = _answers(world, 1.01 * bound, tmp_path / "impossible")
    assert isinstance(rejected, Reject) and "beyond what the world allows" in rejected.reason


# --- bad plugins: one line, an exit status -------------------------------------------------------


@pytest.fixture
def broken_entry_point(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An installed package whose task's entry point names a module that does not exist."""
    info = tmp_path / "broken_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[derl.tasks]\nbroken = no_such_module:task\n")
    monkeypatch.syspath_prepend(str(tmp_path))


@pytest.mark.parametrize(
    ("setting", "reason"),
    [
        ("world=nope", "unknown task 'nope'; choose from ft, vt, mvt"),
        ("world=broken", "entry point 'broken' of group derl.tasks (no_such_module:task) failed "
                         "to load: ModuleNotFoundError"),
        ("world=tests.test_plugins:raising_task", "its factory raised RuntimeError: no terrain"),
        ("selection=tests.test_plugins:outsider", "chose 'c99999', which is not in the pool"),
        ("mutations={tests.test_plugins:junk_operator: 1}", "returned 42, not a (Genome, str)"),
        ("mutations={tests.test_plugins:invalid_operator: 1}", "made no valid child of 3 bodies"),
    ],
)  # fmt: skip
def test_a_bad_plugin_stops_a_run_before_any_node_with_one_line(
    broken_entry_point: None,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    setting: str,
    reason: str,
) -> None:
    argv = ["run", "--profile", "smoke", "--set", setting, "--run-dir", str(tmp_path / "run")]
    with pytest.raises(SystemExit) as ended:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert ended.value.code in (1, 2), err
    assert err.startswith("derl: ") and "\n" not in err and reason in err, err
    assert not (tmp_path / "run").exists()


# --- a real run -----------------------------------------------------------------------------------


def _run(folder: Path, installed: Path) -> Path:
    """A run of the plugins' profile by nodes started one by one: first a trainer that lacks the
    plugins (which refuses), then an evaluator and 2 trainers that hold them, to its end."""
    folder.mkdir()
    local = LocalRun.at(folder, **PLUGIN_PROFILE)
    processes = Processes(folder / "logs")
    held = {"PYTHONPATH": str(installed)}
    try:
        coordinator = processes.start("coordinator", local.coordinator(), held)
        processes.start("lacking", local.trainer("lacking"), {"PYTHONPATH": ""})
        wait_until(
            lambda: [m for m in journaled(local.dir, JobFailed) if m.unfit],
            120,
            "the refusal of the trainer without the plugins",
        )
        evaluator = derl_argv("evaluator", "--run", local.run, "--connect", local.endpoint,
                              "--name", "e0")  # fmt: skip
        processes.start("e0", evaluator, held)
        for k in range(2):
            processes.start(f"t{k}", local.trainer(f"t{k}"), held)
        assert processes.finish(coordinator, timeout=300) == 0, processes.log("coordinator")
    finally:
        processes.close()
    assert_born_once(local.dir, 8)
    return local.dir


def _launched(folder: Path, installed: Path) -> Path:
    """The same run through `derl launch` (a launch file: a coordinator and one trainer, both
    holding the plugins), no evaluator (a run without it evaluates nothing: its births are the
    same)."""
    folder.mkdir()
    port = free_port(span=2)
    unevaluated = {**PLUGIN_PROFILE, "eval_top": 0, "eval_tasks": []}
    profile = write_profile(folder / "profile.yaml", **unevaluated)
    launch = {
        "run": run_id(), "run_dir": str(folder / "run"), "profile": str(profile),
        "topology": {"kind": "peer_mesh", "seed": f"tcp/127.0.0.1:{port}"},
        "hosts": [{"name": "local", "listen": f"tcp/127.0.0.1:{port}", "nodes": [
            {"role": "coordinator", "restart": "never"}, {"role": "trainer", "count": 1}]}],
    }  # fmt: skip
    (folder / "launch.yaml").write_text(yaml.safe_dump(launch))
    processes = Processes(folder / "logs")
    try:
        launcher = processes.start("launch", derl_argv("launch", str(folder / "launch.yaml")),
                                   {"PYTHONPATH": str(installed)})  # fmt: skip
        assert processes.finish(launcher, timeout=300) == 0, processes.log("launch")
    finally:
        processes.close()
    assert_born_once(folder / "run", 8)
    return folder / "run"


@pytest.mark.slow
def test_a_plugin_run_is_refused_by_a_node_without_it_and_gives_one_fingerprint(
    installed: Path, tmp_path: Path
) -> None:
    """Run by nodes started one by one (3 trainers, one lacking the plugins, and an evaluator),
    then through `derl launch` on 1 trainer: one fingerprint; `derl study` of the first retrains
    its bodies in the plugin's world and tests them on it."""
    three = _run(tmp_path / "three", installed)
    refusals = [m for m in journaled(three, JobFailed) if m.unfit]
    assert len(refusals) == 1 and refusals[0].node == "lacking", refusals
    assert "lacks the task plugin stairs (derl-stairs 0.1.0" in refusals[0].error
    assert not [m for m in journaled(three, JobFailed) if not m.unfit]
    assert journaled(three, EvalResult)
    jobs = journaled(three, TrainJob)
    assert {p.name for p in jobs[0].plugins} == {"stairs", "cheap_parents", "stiffen"}
    one = _launched(tmp_path / "one", installed)
    assert load_history(three).fingerprint() == load_history(one).fingerprint()
    study = tmp_path / "study"
    studied = subprocess.run(
        derl_argv("study", str(three), "--study-dir", str(study), "--port", "0", "--workers",
                  "1", "--set", "seeds=1", "--set", "retrain_steps=2048", "--set",
                  "test_tasks=[stairs]", "--set", "budgets=[2048]"),
        env={**os.environ, "PYTHONPATH": str(installed)}, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip
    assert studied.returncode == 0, studied.stdout + studied.stderr
    results = journaled(study, EvalResult)
    assert {r.task for r in results} == {"stairs"} and len(results) >= 2, results


def test_derl_train_and_rollout_take_a_plugin_task(installed: Path, tmp_path: Path) -> None:
    """`derl train --task stairs` and `derl rollout` of its folder, in processes that hold the
    plugin; one that lacks it says so in a line."""
    body = tmp_path / "body.json"
    body.write_text(random_genome(np.random.default_rng(0)).model_dump_json())
    out, env = tmp_path / "trained", {**os.environ, "PYTHONPATH": str(installed)}

    def derl_(*args: str, environment: dict[str, str] = env) -> subprocess.CompletedProcess:
        return subprocess.run(derl_argv(*args), env=environment, cwd=tmp_path, text=True,
                              capture_output=True, timeout=300)  # fmt: skip

    trained = derl_("train", "--genome", str(body), "--task", "stairs", "--steps", "2048",
                    "--envs", "16", "--out", str(out))  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    played = derl_("rollout", str(out), "--episodes", "1", "--episode-steps", "20")
    assert played.returncode == 0, played.stderr
    assert "progress" in played.stdout, played.stdout
    lacking = derl_("rollout", str(out), environment={**os.environ, "PYTHONPATH": ""})
    assert lacking.returncode != 0
    assert lacking.stderr.strip().splitlines()[-1].startswith("derl: "), lacking.stderr
    assert "unknown task 'stairs'" in lacking.stderr, lacking.stderr


# --- the built-in schemes, weights and refusals, without a plugin ------------------------------


def test_equal_operator_weights_are_the_papers_draw_and_weights_share_the_draws() -> None:
    rng = np.random.default_rng(5)
    bodies = [random_genome(rng) for _ in range(6)]
    uniform = dict.fromkeys(OPERATORS, 1.0)
    for k, body in enumerate(bodies):
        assert mutate(body, np.random.default_rng(k)) == mutate(
            body, np.random.default_rng(k), weights=uniform
        )
    drawn = Counter(
        mutate(bodies[k % 6], np.random.default_rng(k), weights={"gear": 3.0, "dof": 1.0})[1].op
        for k in range(240)
    )
    assert set(drawn) == {"gear", "dof"} and 2.0 < drawn["gear"] / drawn["dof"] < 5.0, drawn


def test_a_pareto_parent_is_never_beaten_on_both_fitness_and_cost() -> None:
    pool = [Member(f"i{k:04d}", float(k % 5), None, k, cost_of_work=float(k % 3)) for k in range(9)]
    scheme = make_selection("pareto")
    for iteration in range(50):
        positions, _ = tournament_draws(0, iteration, 4, len(pool))
        chosen = select("pareto", scheme, pool, Draws(tuple(positions), 0, iteration))
        parent = chosen.parent
        assert parent in chosen.contestants
        assert not any(
            m.fitness >= parent.fitness
            and m.cost_of_work <= parent.cost_of_work
            and (m.fitness, -m.cost_of_work) != (parent.fitness, -parent.cost_of_work)
            for m in chosen.contestants
        )


def test_a_worker_that_refuses_a_run_gets_no_more_jobs_and_costs_no_attempt(
    tmp_path: Path,
) -> None:
    run, heard = "tunfit", Recorder()
    config = load_profile("smoke").model_copy(update={"eval_top": 0, "eval_tasks": ()})
    coordinator = Coordinator(run, tmp_path, EvolutionRules(run, tmp_path, config), heard)
    try:
        for node in ("lacking", "holding"):
            coordinator.take(Liveliness("trainer", node, True))
        ask = {
            n: WorkerReady(run=run, node=n, role="trainer", host="h", pid=1)
            for n in ("lacking", "holding")
        }
        coordinator.take(ask["lacking"])
        coordinator.settle()
        job = next(m for m in heard.messages if isinstance(m, TrainJob))
        refusal = JobFailed(run=run, job=job.job, node="lacking", agent=job.agent,
                            error="lacks the task plugin x", unfit=True)  # fmt: skip
        coordinator.take(refusal)
        coordinator.take(ask["lacking"])
        coordinator.take(ask["holding"])
        coordinator.settle()
        jobs = [m for m in heard.messages if isinstance(m, TrainJob)]
        assert [j.node for j in jobs] == ["lacking", "holding"], jobs
        assert jobs[1].agent == job.agent  # the refused child, first in line again
        assert coordinator.state.unfit == {"lacking": "lacks the task plugin x"}
        assert coordinator.state.failures == {}
    finally:
        coordinator.close()
