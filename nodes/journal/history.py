"""The one reading of a run's journal: its messages folded, in order, into the run's facts.

`RunHistory.apply` dispatches each message to its handler (`derl.messages.dispatch`), which
records what it means: a TrainJob or EvalJob assigns work (the first one says the run's world
and budget), the FitnessReport the coordinator accepted is the evidence of a birth (its learning
curve is kept) and the Birth that follows it is the birth (index, generation, fitness), a
ChildFailed gives a child up, an EvalResult completes an evaluation, a Quarantine names a
trainer caught lying, a Retrained replaces a child's result, an Undo forgets the children of the
tournaments decided again after a caught lie, and a Dropped those dropped at the released end.
Every reader uses it: the coordinator's states (`nodes.coordinator.jobs` and the states built on
it extend the handlers to keep the jobs in flight, and keep no learning curves), `derl report`
and `derl study` (`run_log`), the monitor."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from derl.evolution.evolution import tournament_child
from derl.evolution.fingerprint import child_order, fingerprint
from derl.messages import (
    Birth,
    ChildFailed,
    Dropped,
    EvalJob,
    EvalResult,
    FitnessReport,
    JobFailed,
    JobLost,
    MessageBase,
    Quarantine,
    Retrained,
    RunSettings,
    TrainJob,
    Undo,
)
from derl.messages.dispatch import Handler, handles
from derl.nodes.errors import USAGE, DerlError
from derl.nodes.journal.segments import (
    JournalDamaged,
    is_mcap,
    read_segment,
    replay,
    segments,
)
from derl.nodes.runtime.checkpoints import FOLDER as CHECKPOINTS

if TYPE_CHECKING:
    from derl.analysis import RunLog

log = logging.getLogger("derl.history")

EvalKey = tuple[str, str, int, int]  # (agent, task, seed, steps)


class RunHistory(Handler):
    """What a run's journal says happened; `apply` its messages in journal order."""

    def __init__(self) -> None:
        self.run: str | None = None
        self.first_job: TrainJob | None = None  # the run's first (its world and budget)
        self.issued: dict[str, tuple[str, str]] = {}  # every job ever sent -> (node, agent)
        self.births: list[Birth] = []  # in birth order
        self.born: dict[str, Birth] = {}
        self.repeats = 0  # births with the result of an earlier body's (`Birth.repeat_of`)
        self.reports: dict[str, FitnessReport] = {}  # child -> the report it was born from
        self.failed: dict[str, ChildFailed] = {}
        self.failures: dict[str, list[JobFailed]] = {}  # agent -> its failed jobs
        self.unfit: dict[str, str] = {}  # node -> why it refused the run's jobs (JobFailed.unfit)
        self.lost: list[JobLost] = []
        self.evaluations: dict[EvalKey, EvalResult] = {}
        self.checked_births: set[str] = set()  # born from two or more trainings (an audit)
        self.quarantined: dict[str, Quarantine] = {}  # identity -> the quarantine that caught it
        self.retrained: dict[str, Retrained] = {}  # child -> its result's replacement
        self.kept_reports: dict[str, FitnessReport] = {}  # an undone child's job -> its report
        self.dropped: set[str] = set()  # children dropped at the released end (`Dropped`)
        self.other_runs = 0
        self.settings: list[str] = []  # the run's settings as JSON, each time they were set
        self._accepted: dict[str, list[FitnessReport]] = {}  # child -> its reports, until born

    def fingerprint(self) -> str:
        """The run's fingerprint (`derl.evolution.fingerprint`) over its births so far and the
        plugins its jobs named."""
        plugins = () if self.first_job is None else self.first_job.plugins
        return fingerprint(
            ((b.agent, b.parent, b.generation, b.fitness, b.genome) for b in self.births),
            tuple(plugin.model_dump_json() for plugin in plugins),
        )

    def apply(self, msg: MessageBase) -> None:
        if self.run is None:
            self.run = msg.run
        elif msg.run != self.run:
            self.other_runs += 1
            return
        self.dispatch(msg)

    # --- handlers (the coordinator's state extends them) -------------------------------------

    def issued_to(self, job: str, node: str, agent: str) -> bool:
        """Whether `job` was given to `node` for `agent` (a child, or an evaluated agent)."""
        return self.issued.get(job) == (node, agent)

    @handles(RunSettings)
    def on_settings(self, msg: RunSettings) -> None:
        self.settings.append(msg.settings)

    @handles(TrainJob)
    def on_train_job(self, msg: TrainJob) -> None:
        self.issued[msg.job] = (msg.node, msg.agent)
        if self.first_job is None:
            self.first_job = msg

    @handles(EvalJob)
    def on_eval_job(self, msg: EvalJob) -> None:
        self.issued[msg.job] = (msg.node, msg.agent)

    @handles(FitnessReport)
    def on_fitness_report(self, msg: FitnessReport) -> None:
        self._accepted.setdefault(msg.agent, []).append(msg)

    @handles(Birth)
    def on_birth(self, msg: Birth) -> None:
        if msg.agent in self.born:
            return
        self.births.append(msg)
        self.born[msg.agent] = msg
        reports = self._accepted.pop(msg.agent, [])
        if len(reports) > 1:
            self.checked_births.add(msg.agent)
        report = next((r for r in reports if r.job == msg.job), None)
        if msg.repeat_of is not None:
            self.repeats += 1
            if report is None:
                report = self.reports.get(msg.repeat_of)
        if report is None:  # born from an undone child's training (`Undo`)
            report = self.kept_reports.get(msg.job)
        if report is not None:
            self.reports[msg.agent] = report

    @handles(ChildFailed)
    def on_child_failed(self, msg: ChildFailed) -> None:
        self.failed.setdefault(msg.agent, msg)

    @handles(Quarantine)
    def on_quarantine(self, msg: Quarantine) -> None:
        self.quarantined.setdefault(msg.node, msg)

    @handles(Retrained)
    def on_retrained(self, msg: Retrained) -> None:
        """The child's result, and its repeats', is the new training's from now on."""
        if msg.agent not in self.born:
            return
        self.retrained[msg.agent] = msg
        report = next((r for r in self._accepted.pop(msg.agent, []) if r.job == msg.job), None)
        fields = ("job", "node", "fitness", "cost_of_work", "energy", "mass")
        result = {k: getattr(msg, k) for k in fields}
        if msg.episodes is not None and msg.constraint_rows is not None:
            result.update(episodes=msg.episodes, constraint_rows=msg.constraint_rows)
        for k, birth in enumerate(self.births):
            if msg.agent in (birth.agent, birth.repeat_of):
                self.births[k] = self.born[birth.agent] = birth.model_copy(update=result)
                if report is not None:
                    self.reports[birth.agent] = report

    @handles(Undo)
    def on_undo(self, msg: Undo) -> None:
        """The children of the tournaments from `msg.iteration` on are forgotten (`_forget`)."""
        first = child_order(tournament_child(msg.iteration))
        self._forget(lambda agent: child_order(agent) >= first)

    @handles(Dropped)
    def on_dropped(self, msg: Dropped) -> None:
        """The children dropped at the released end are forgotten (`_forget`)."""
        dropped = set(msg.agents)
        self.dropped.update(dropped)
        self._forget(dropped.__contains__)

    def _forget(self, gone: Callable[[str], bool]) -> None:
        """The agents `gone` says are forgotten: their births, failures and results (a birth
        that was a repeat of one is its own); the report each was born from is kept by its job
        (`kept_reports`, for a child born from an undone child's training)."""
        for birth in self.births:
            if gone(birth.agent) and birth.agent in self.reports:
                self.kept_reports[birth.job] = self.reports.pop(birth.agent)
        self.births = [
            b.model_copy(update={"repeat_of": None})
            if b.repeat_of is not None and gone(b.repeat_of)
            else b
            for b in self.births
            if not gone(b.agent)
        ]
        self.born = {b.agent: b for b in self.births}
        self.repeats = sum(b.repeat_of is not None for b in self.births)
        self.checked_births = {a for a in self.checked_births if not gone(a)}
        for table in (self.failed, self.failures, self.retrained, self._accepted):
            for agent in [a for a in table if gone(a)]:
                del table[agent]

    @handles(JobFailed)
    def on_job_failed(self, msg: JobFailed) -> None:
        if msg.unfit:
            self.unfit.setdefault(msg.node, msg.error)
        else:
            self.failures.setdefault(msg.agent, []).append(msg)

    @handles(JobLost)
    def on_job_lost(self, msg: JobLost) -> None:
        self.lost.append(msg)

    @handles(EvalResult)
    def on_eval_result(self, msg: EvalResult) -> None:
        self.evaluations.setdefault((msg.agent, msg.task, msg.seed, msg.steps), msg)

    # --- questions --------------------------------------------------------------------------

    @property
    def audited(self) -> int:
        """Births from two or more trainings (an audit: `EvolutionConfig.audit`)."""
        return len(self.checked_births)

    def generation(self, parent: str | None) -> int:
        """The generation of a child of `parent` (0 for the initial population)."""
        return 0 if parent is None else self.born[parent].generation + 1


def journal_run(run_dir: Path) -> str | None:
    """The run id of the journal in `run_dir` (its first message's), None without one."""
    if not segments(run_dir):
        return None
    try:
        first = next(replay(run_dir), None)
    except JournalDamaged:
        return None  # the coordinator says so when it starts
    return None if first is None else first.run


def load_history(path: Path) -> RunHistory:
    """The history of a run directory's journal, or of one MCAP file (a segment, a recording);
    `DerlError` with the reason when there is none."""
    if path.is_dir():  # read as every tool reads: past a damaged part, with a warning
        if not segments(path):
            raise DerlError(f"{path} holds no journal (journal/segment-NNNN.mcap)")
        messages: Iterable[MessageBase] = (
            msg for segment in segments(path) for msg in read_segment(segment)
        )
    elif path.is_file():
        if not is_mcap(path):
            raise DerlError(f"{path} is not an MCAP log (a run directory, a journal "
                            "segment or a `derl record` file)")  # fmt: skip
        messages = read_segment(path)
    else:
        raise DerlError(f"no run directory or log at {path}", USAGE)
    history = RunHistory()
    for msg in messages:
        history.apply(msg)
    if history.other_runs:
        log.warning("%s: %d messages of runs other than %s skipped", path, history.other_runs,
                    history.run)  # fmt: skip
    return history


def run_log(path: Path) -> RunLog:
    """A run's records for `derl.analysis`, from its journal (see `load_history`): the bodies
    in child order (the order they were bred: the same in every run of the seed, whatever
    order their trainings finished in), `Body.birth` their place in it."""
    from derl.analysis import Body, Evaluation, RunLog

    history = load_history(path)
    bodies = []
    in_child_order = sorted(history.births, key=lambda b: child_order(b.agent))
    for place, birth in enumerate(in_child_order):
        report = history.reports.get(birth.agent)
        bodies.append(
            Body(
                id=birth.agent,
                parent=birth.parent,
                birth=place,
                fitness=birth.fitness,
                curve_steps=report.curve.env_steps if report else (),
                curve_returns=report.curve.returns if report else (),
                energy=birth.energy,
                cost_of_work=birth.cost_of_work,
                mass=birth.mass,
                mutation=birth.mutation,
                genome=birth.genome,
                repeat_of=birth.repeat_of,
            )
        )
    if not bodies:
        raise DerlError(f"no body was born in {path}")
    first = history.first_job
    if first is None:
        raise DerlError(f"{path}: bodies were born but no training job is journaled")
    evaluations = tuple(
        Evaluation(
            agent=r.agent,
            task=r.task,
            seed=r.seed,
            steps=r.steps,
            reward=r.reward,
            cost_of_work=r.cost_of_work,
        )
        for r in history.evaluations.values()
    )
    return RunLog(
        name=history.run,
        world=first.task,
        bodies=tuple(bodies),
        evaluations=evaluations,
        train_steps=first.steps,
        training_seed=first.seed,
        checkpoints=path / CHECKPOINTS if (path / CHECKPOINTS).is_dir() else None,
        fingerprint=history.fingerprint(),
        audited=history.audited,
        quarantined=tuple(history.quarantined),
    )


def load_runs(paths: list[Path]) -> list[RunLog]:
    """The runs of `paths`, renamed run-2, run-3... where two carry the same run id."""
    runs, seen = [], set()
    for path in paths:
        run = run_log(path)
        name, k = run.name, 1
        while name in seen:
            k += 1
            name = f"{run.name}-{k}"
        seen.add(name)
        runs.append(run if name == run.name else run.model_copy(update={"name": name}))
    return runs
