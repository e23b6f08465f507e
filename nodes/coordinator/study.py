"""A study's policy: the paper's appendix D as evaluation jobs, journaled like a run.

A study directory holds what the study is and the bodies it retrains (`study_files`). Its
coordinator is the run's node loop with this policy and another state: first every planned
retraining (a selected body in its own world with a new seed), then, once each has its result or
was given up, the test stage: per world, the `top` of the `keep` best bodies by mean retrained
fitness, on every test task with every test seed at every budget. The test stage is derived from
the journal's results, so a restarted coordinator plans it again, identically. Only evaluators
get work; at the end it writes `selection.json` (per world the kept and the tested bodies with
their mean fitness) and `summary.json` (every result).
"""

from __future__ import annotations

import json
import logging
from functools import partial
from pathlib import Path

from derl.analysis.selection import RetrainJob, RetrainPlan, kept_bodies
from derl.analysis.study import StudyConfig
from derl.messages import (
    EvalJob,
    EvalResult,
    FitnessReport,
    JobFailed,
    MessageBase,
    PopulationSnapshot,
    TrainJob,
)
from derl.nodes.coordinator.evaluations import evaluation_job, log_given_up, on_evaluation
from derl.nodes.coordinator.ledger import Ledger
from derl.nodes.coordinator.node import serve
from derl.nodes.coordinator.policy import Progress
from derl.nodes.coordinator.state import CoordinatorState, Job
from derl.nodes.coordinator.study_files import (
    StudyRequest,
    prepare_study,
    read_plan,
    read_setup,
    selected_bodies,
    study_agent,
)
from derl.nodes.errors import Refused
from derl.nodes.journal.history import EvalKey
from derl.nodes.runtime.bus import ZenohOptions
from derl.nodes.runtime.rundir import write_atomic
from derl.rl import PPOConfig
from derl.unimal import Genome

log = logging.getLogger("derl.study")


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


class StudyPolicy:
    """The policy of the study in `study_dir`: evaluators retrain and test; trainers get nothing.
    Given the runs and settings of `request`, it makes the study there first if there is none."""

    def __init__(self, run: str, study_dir: Path, request: StudyRequest) -> None:
        self.run, self.study_dir = run, study_dir
        if request.runs and request.config is not None:
            self.config = prepare_study(study_dir, request.runs, request.config).config
        else:
            self.config = read_setup(study_dir).config
        plan = read_plan(study_dir)
        for job in plan.jobs:
            self._check_job(study_agent(job), job)
        self.state = StudyState(self.config, plan)

    def _check_job(self, agent: str, job: RetrainJob) -> None:
        if len(agent) > 128:
            raise Refused(f"study agent name {agent!r} is longer than 128 characters")
        if job.steps is None and self.config.retrain_steps is None:
            raise Refused(f"{job.run} records no lifetime budget: set retrain_steps")

    def start(self, ledger: Ledger) -> None:
        self.ledger = ledger

    def next_job(self, node: str, role: str, trainers: int) -> TrainJob | EvalJob | None:
        if role == "trainer":
            return None  # a study has evaluations only
        return evaluation_job(self.state, self.run, node, self.config.lease_s)

    def on_fitness(self, report: FitnessReport) -> None:
        self.ledger.never_issued(report, report.child)  # a study trains no children

    def on_evaluation(self, result: EvalResult) -> None:
        on_evaluation(self.ledger, result)

    def on_failure(self, failure: JobFailed, job: Job) -> None:
        log_given_up(self.state, job, self.config.max_attempts)

    def progress(self) -> Progress:
        return Progress()  # no children

    def snapshot(self) -> PopulationSnapshot:
        return PopulationSnapshot(run=self.run, birth_counter=0, members=())

    def log_progress(self) -> None:
        state = self.state
        log.info("study %s: %d/%d evaluations, %d in flight", self.run, state.evaluated,
                 state.eval_target, len(state.jobs))  # fmt: skip

    def finish(self) -> None:
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
        write_atomic(self.study_dir / "selection.json", json.dumps(selection, indent=2) + "\n")
        summary = {
            "study": self.run,
            "profile": self.config.model_dump(),
            "given_up": [list(key) for key in sorted(state.eval_given_up)],
            "results": [r.model_dump(exclude={"curve"}) for r in state.evaluations.values()],
        }
        write_atomic(self.study_dir / "summary.json", json.dumps(summary, indent=2) + "\n")
        log.info("study %s finished: results in %s", self.run, self.study_dir)

    def _entry(self, agent: str, mean: float) -> dict[str, object]:
        job = self.state.selected[agent]
        seeds = sum(key[0] == agent for key in self.state.retraining)
        return {"run": job.run, "agent": job.agent, "lineage": job.lineage,
                "evolution_fitness": job.fitness, "mean_fitness": mean, "seeds": seeds}  # fmt: skip


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
    policy = partial(StudyPolicy, run, study_dir, StudyRequest(runs or [], config))
    return serve(run, study_dir, policy, options)
