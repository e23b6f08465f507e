"""A study's rules: the paper's appendix D as evaluation jobs, journaled like a run.

A study directory holds what the study is and the bodies it retrains (`files`). Its
coordinator is the run's node loop with these rules and its own state (`state`: the
retrainings, then the tests of the best retrained bodies, as evaluations). Only evaluators get
work; at the end it writes `selection.json` (per world the kept and the tested bodies with
their mean fitness) and `summary.json` (every result).
"""

from __future__ import annotations

import json
import logging
from functools import partial
from pathlib import Path

from derl.analysis.study import StudyConfig
from derl.envs.registry import TASK_REGISTRY
from derl.messages import (
    EvalJob,
    EvalResult,
    FitnessReport,
    JobFailed,
    PopulationSnapshot,
    TrainJob,
)
from derl.nodes.coordinator.evaluations import evaluation_job, log_given_up, on_evaluation
from derl.nodes.coordinator.jobs import Job
from derl.nodes.coordinator.ledger import Ledger
from derl.nodes.coordinator.node import serve
from derl.nodes.coordinator.rules import Progress
from derl.nodes.coordinator.study.files import StudyRequest, prepare_study, read_plan, read_setup
from derl.nodes.coordinator.study.state import StudyState
from derl.nodes.runtime.bus import ZenohOptions
from derl.nodes.runtime.rundir import write_atomic

log = logging.getLogger("derl.study")


class StudyRules:
    """The rules of the study in `study_dir`: evaluators retrain and test; trainers get nothing.
    Given the runs and settings of `request`, it makes the study there first if there is none."""

    def __init__(self, run: str, study_dir: Path, request: StudyRequest) -> None:
        self.run, self.study_dir = run, study_dir
        if request.runs and request.config is not None:
            self.config = prepare_study(study_dir, request.runs, request.config).config
        else:
            self.config = read_setup(study_dir).config
        self.state = StudyState(self.config, read_plan(study_dir))
        tasks = dict.fromkeys([*self.state.worlds, *self.config.test_tasks])
        found = (TASK_REGISTRY.identity(task) for task in tasks)
        self.plugins = tuple(plugin for plugin in found if plugin is not None)

    def start(self, ledger: Ledger) -> None:
        self.ledger = ledger

    def next_job(self, node: str, role: str, trainers: int) -> TrainJob | EvalJob | None:
        if role == "trainer":
            return None  # a study has evaluations only
        return evaluation_job(self.state, self.run, node, self.config.lease_s, self.plugins)

    def on_fitness(self, report: FitnessReport) -> None:
        self.ledger.never_issued(report, report.agent)  # a study trains no children

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
        seeds = sum(key[0] == agent for key in self.state.retrainings)
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
    rules = partial(StudyRules, run, study_dir, StudyRequest(runs or [], config))
    return serve(run, study_dir, rules, options)
