"""A study directory's files: what the study is, the bodies it retrains, and its runs as a report.

`study.json` holds the study's settings and the runs it reads (`StudySetup`); `plan.json` the
retraining jobs `derl.analysis.plan` chose from the runs' journals: a decision, kept as a fact,
so a restarted study never chooses again from runs that grew since (`prepare_study` makes both).
An agent of a study is named ``<run>.<agent>``. `study_logs` reads a study back for
`derl report`. At the end its coordinator writes `selection.json` and `summary.json`
(`study.StudyRules.finish`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from derl.analysis.selection import RetrainJob, RetrainPlan
from derl.analysis.study import StudyConfig
from derl.nodes.errors import DerlError, Refused
from derl.nodes.journal.history import load_history, load_runs
from derl.nodes.runtime.rundir import write_atomic
from derl.rl.config import SAVED
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


def read_setup(study_dir: Path) -> StudySetup:
    return _read(study_dir / SETUP_FILE, StudySetup, context=SAVED)


def read_plan(study_dir: Path) -> RetrainPlan:
    return _read(study_dir / PLAN_FILE, RetrainPlan)


def _read(path: Path, model: type[M], context: Mapping[str, object] | None = None) -> M:
    try:
        return model.model_validate_json(path.read_text(), context=context)
    except FileNotFoundError:
        raise Refused(f"{path.parent} is not a study (no {path.name}): start it with "
                      "`derl study RUN_DIR... --study-dir DIR`") from None  # fmt: skip
    except OSError as error:
        raise Refused(f"{path} is not readable: {error}") from None
    except ValidationError as error:
        raise Refused(f"{path} is not valid: {problems(error)}") from None


def prepare_study(study_dir: Path, runs: list[Path], config: StudyConfig) -> StudySetup:
    """Make `study_dir` a study of `runs` with `config`: its setup and its retraining plan,
    chosen now from the runs' journals. A study begun there already keeps its own (and says so
    where `runs` or `config` differ); `Refused` with the reason when the runs cannot be read."""
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
        raise Refused(f"{study_dir} is not a study yet: give the run directories")
    for path in runs:
        if path.is_dir() and not (path / "summary.json").exists():
            log.warning("%s is not finished (no summary.json): its surviving lineages are those "
                        "of its population now", path)  # fmt: skip
    try:
        logs = load_runs(runs)
    except DerlError as error:  # a run directory without a journal, or without a birth
        raise Refused(str(error)) from None
    chosen = plan(logs, config.per_lineage, config.seeds, config.seed)
    if not chosen.jobs:
        raise Refused("the runs have no surviving lineage to select from")
    setup = StudySetup(config=config, runs=tuple(p.resolve() for p in runs))
    study_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(study_dir / PLAN_FILE, chosen.model_dump_json(indent=2) + "\n")
    write_atomic(study_dir / SETUP_FILE, setup.model_dump_json(indent=2) + "\n")
    return setup


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
