"""A study's coordinator: the paper's appendix D as jobs for evaluator nodes, journaled like a run.

A study directory holds `study.json` (its settings and the runs it reads) and `plan.json` (the
retraining jobs `derl.analysis.plan` chose from the runs' journals: a decision, kept as a fact, so
a restarted study never chooses again from runs that grew since). Its coordinator is the run's
(`Coordinator`: journal, group commit, leases, acknowledgements, restarts) with another state:
first every planned retraining (a selected body in its own world with a new seed), then, once each
has its result or was given up, the test stage: per world, the `top` of the `keep` best bodies by
mean retrained fitness, on every test task with every test seed at every budget. The test stage
is derived from the journal's results, so a restarted coordinator plans it again, identically.
An agent of a study is named ``<run>.<agent>``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from derl.messages import MessageBase, PopulationSnapshot, RunStatus
from derl.nodes.coordinator.node import Coordinator, serve
from derl.nodes.coordinator.state import CoordinatorState
from derl.nodes.journal.history import EvalKey, load_history, load_runs
from derl.nodes.runtime.bus import ZenohOptions
from derl.nodes.runtime.rundir import write_atomic
from pydantic import BaseModel, ConfigDict, ValidationError

from derl.analysis.selection import RetrainJob, RetrainPlan, kept_bodies
from derl.analysis.study import StudyConfig
from derl.rl import PPOConfig
from derl.rl.config import SAVED
from derl.unimal import Genome
from derl.validation import problems

if TYPE_CHECKING:
    from derl.analysis import RunLog

log = logging.getLogger("derl.study")

M = TypeVar("M", bound=BaseModel)

SETUP_FILE = "study.json"
PLAN_FILE = "plan.json"


class StudySetup(BaseModel):
    """`study.json`: what a study is (its settings and the run directories it selects from)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    config: StudyConfig
    runs: tuple[Path, ...]


@dataclass
class StudyRequest:
    """What a study coordinator is started with: the runs and settings of a study to make in
    its directory if there is none yet (none given: the directory must hold one)."""

    runs: list[Path]
    config: StudyConfig | None = None


def study_agent(job: RetrainJob) -> str:
    """A selected body's name in the study: its run's and its own."""
    return f"{job.run}.{job.agent}"


def selected_bodies(plan: RetrainPlan) -> dict[str, RetrainJob]:
    """The plan's bodies by their name in the study (one of each body's jobs)."""
    return {study_agent(job): job for job in plan.jobs}


class StudyState(CoordinatorState):
    """The jobs in flight (the run's bookkeeping) and appendix D's two stages as evaluations."""

    def __init__(self, config: StudyConfig, plan: RetrainPlan) -> None:
        super().__init__(config, None)  # type: ignore[arg-type]  # no evolution in a study
        self.config: StudyConfig = config
        self.selected = selected_bodies(plan)  # agent -> its body
        self.retraining = [
            (study_agent(job), job.task, job.seed, config.retrain_steps or job.steps)
            for job in plan.jobs
        ]
        self.worlds = list(dict.fromkeys(job.task for job in plan.jobs))
        self.tested: dict[str, list[tuple[str, float]]] = {}  # world -> (agent, mean), planned

    def known(self, msg: MessageBase) -> bool:
        """Every message: a study decides no children (it has no evolution to check them by)."""
        return True

    def _plan_evaluations(self) -> None:
        if not self.planned:
            for key in self.retraining:
                self._plan(key)
        if self.tested or not self.evaluations_over(self.retraining):
            return
        config = self.config
        for world, kept in self.kept().items():
            self.tested[world] = kept[: config.top]
            for agent, _ in self.tested[world]:
                for task in config.test_tasks:
                    for steps in config.budgets:
                        for seed in range(config.test_seeds):
                            self._plan((agent, task, seed, steps))

    def kept(self) -> dict[str, list[tuple[str, float]]]:
        """Per world, the `keep` best retrained bodies by mean fitness over their new seeds (each
        body once, ranked only with every seed's result: `derl.analysis.selection.kept_bodies`)."""
        results = [
            (key[0], key[2], self.evaluations[key].reward)
            for key in self.retraining
            if key in self.evaluations
        ]
        return kept_bodies(self.selected, results, self.config.keep)

    def evaluation_order(self, key: EvalKey) -> tuple[Genome, PPOConfig]:
        agent, task, seed, steps = key
        return self.selected[agent].genome, self.config.job_ppo(task, steps, seed)

    @property
    def eval_target(self) -> int:
        """The retrainings, and the tests of at most `top` bodies per world."""
        config = self.config
        per_body = len(config.test_tasks) * len(config.budgets) * config.test_seeds
        bodies = {w: sum(j.task == w for j in self.selected.values()) for w in self.worlds}
        tested = sum(min(config.top, n) for n in bodies.values())
        if self.tested:
            tested = sum(len(agents) for agents in self.tested.values())
        return len(self.retraining) + tested * per_body

    @property
    def finished(self) -> bool:
        self._plan_evaluations()
        return bool(self.tested) and self.evaluations_over(self.planned)


class StudyCoordinator(Coordinator):
    """The coordinator of a study: evaluators retrain and test; trainers get nothing."""

    config: StudyConfig
    state: StudyState

    @property
    def born(self) -> int:
        return 0

    def _run_config(self, given: StudyRequest) -> StudyConfig:  # type: ignore[override]
        """The study's settings as `study.json` holds them, made now from the request's runs
        if there is none yet (see `prepare_study`)."""
        if given.runs and given.config is not None:
            return prepare_study(self.run_dir, given.runs, given.config).config
        return read_setup(self.run_dir).config

    def _new_state(self) -> StudyState:  # type: ignore[override]
        plan = read_plan(self.run_dir)
        for job in plan.jobs:
            self._check_job(study_agent(job), job)
        return StudyState(self.config, plan)

    def _check_job(self, agent: str, job: RetrainJob) -> None:
        if len(agent) > 128:
            raise SystemExit(f"derl: study agent name {agent!r} is longer than 128 characters")
        if job.steps is None and self.config.retrain_steps is None:
            raise SystemExit(f"derl: {job.run} records no lifetime budget: set retrain_steps")

    def _resume(self) -> None:
        pass

    def _assign_training(self, node: str) -> None:
        pass  # a study has evaluations only

    def _log_births(self) -> None:
        state = self.state
        log.info("study %s: %d/%d evaluations, %d in flight", self.run, state.evaluated,
                 state.eval_target, len(state.jobs))  # fmt: skip

    def _status(self) -> RunStatus:
        return RunStatus(
            run=self.run,
            born=0,
            target=0,
            in_flight=len(self.state.jobs),
            workers_alive=len(self.alive),
            evaluated=self.state.evaluated,
            eval_target=self.state.eval_target,
            rejected=self.rejected,
            steps_per_s=sum(self.rates.values()),
            done=self.state.finished,
        )

    def _snapshot(self) -> PopulationSnapshot:
        return PopulationSnapshot(run=self.run, birth_counter=0, members=())

    def _write_results(self) -> None:
        """`selection.json`: per world, the kept bodies by mean retrained fitness and the tested
        ones; `summary.json`: every result."""
        state = self.state
        selection = {
            world: {
                "kept": [self._entry(agent, mean) for agent, mean in kept],
                "tested": [self._entry(agent, mean) for agent, mean in state.tested.get(world, [])],
            }
            for world, kept in state.kept().items()
        }
        write_atomic(self.run_dir / "selection.json", json.dumps(selection, indent=2) + "\n")
        summary = {
            "study": self.run,
            "profile": self.config.model_dump(),
            "given_up": [list(key) for key in sorted(state.eval_given_up)],
            "results": [r.model_dump(exclude={"curve"}) for r in state.evaluations.values()],
        }
        write_atomic(self.run_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
        log.info("study %s finished: results in %s", self.run, self.run_dir)

    def _entry(self, agent: str, mean: float) -> dict[str, object]:
        job = self.state.selected[agent]
        seeds = sum(key[0] == agent for key in self.state.retraining)
        return {"run": job.run, "agent": job.agent, "lineage": job.lineage,
                "evolution_fitness": job.fitness, "mean_fitness": mean, "seeds": seeds}  # fmt: skip


def read_setup(study_dir: Path) -> StudySetup:
    return _read(study_dir / SETUP_FILE, StudySetup, context=SAVED)


def read_plan(study_dir: Path) -> RetrainPlan:
    return _read(study_dir / PLAN_FILE, RetrainPlan)


def _read(path: Path, model: type[M], context: dict[str, object] | None = None) -> M:
    try:
        return model.model_validate_json(path.read_text(), context=context)
    except FileNotFoundError:
        raise SystemExit(f"derl: {path.parent} is not a study (no {path.name}): start it with "
                         "`derl study RUN_DIR... --study-dir DIR`") from None  # fmt: skip
    except OSError as error:
        raise SystemExit(f"derl: {path} is not readable: {error}") from None
    except ValidationError as error:
        raise SystemExit(f"derl: {path} is not valid: {problems(error)}") from None


def prepare_study(study_dir: Path, runs: list[Path], config: StudyConfig) -> StudySetup:
    """Make `study_dir` a study of `runs` with `config`: its setup and its retraining plan,
    chosen now from the runs' journals. A study begun there already keeps its own (and says so
    where `runs` or `config` differ); SystemExit with the reason when the runs cannot be read."""
    from derl.analysis import plan

    if (study_dir / SETUP_FILE).exists():
        setup = read_setup(study_dir)
        read_plan(study_dir)
        if runs and [p.resolve() for p in runs] != list(setup.runs):
            log.warning("%s studies %s; the runs given are ignored", study_dir,
                        ", ".join(map(str, setup.runs)))  # fmt: skip
        if config != setup.config:
            log.warning("%s keeps its settings (profile %s)", study_dir, setup.config.name)
        return setup
    if not runs:
        raise SystemExit(f"derl: {study_dir} is not a study yet: give the run directories")
    for path in runs:
        if path.is_dir() and not (path / "summary.json").exists():
            log.warning("%s is not finished (no summary.json): its surviving lineages are those "
                        "of its population now", path)  # fmt: skip
    chosen = plan(load_runs(runs), config.per_lineage, config.seeds, config.seed)
    if not chosen.jobs:
        raise SystemExit("derl: the runs have no surviving lineage to select from")
    setup = StudySetup(config=config, runs=tuple(p.resolve() for p in runs))
    study_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(study_dir / PLAN_FILE, chosen.model_dump_json(indent=2) + "\n")
    write_atomic(study_dir / SETUP_FILE, setup.model_dump_json(indent=2) + "\n")
    return setup


def serve_study(
    run: str,
    study_dir: Path,
    options: ZenohOptions,
    runs: list[Path] | None = None,
    config: StudyConfig | None = None,
) -> bool:
    """The coordinator of the study in `study_dir` until it is finished (True) or stopped;
    given `runs` and `config`, it makes the study there first if there is none yet."""
    if not runs:
        read_setup(study_dir)  # a study, before anything is made there
    return serve(run, study_dir, StudyRequest(runs or [], config), options, StudyCoordinator)


def study_logs(study_dir: Path) -> list[RunLog]:
    """The study's runs with its results, for `derl report`: each run's retrainings, and as its
    evaluations the test results of its tested bodies (the runs' own are left out)."""
    from derl.analysis import Evaluation, Retraining

    setup, plan = read_setup(study_dir), read_plan(study_dir)
    selected = selected_bodies(plan)
    retrained: dict[str, list[Retraining]] = {}
    tested: dict[str, list[Evaluation]] = {}
    for (agent, task, seed, steps), result in load_history(study_dir).evaluations.items():
        job = selected.get(agent)
        if job is None:
            continue
        own = {"agent": job.agent, "seed": seed, "steps": steps,
               "cost_of_work": result.cost_of_work}  # fmt: skip
        if task == job.task:
            retrained.setdefault(job.run, []).append(Retraining(**own, fitness=result.reward))
        else:
            tested.setdefault(job.run, []).append(
                Evaluation(**own, task=task, reward=result.reward)
            )
    return [
        run.model_copy(
            update={
                "retrained": tuple(retrained.get(run.name, ())),
                "evaluations": tuple(tested.get(run.name, ())),
            }
        )
        for run in load_runs(list(setup.runs))
    ]
