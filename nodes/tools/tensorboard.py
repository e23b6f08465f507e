"""`derl tensorboard` and `derl export --tensorboard`: a run's curves as TensorBoard event files.

RL researchers watch training in TensorBoard (Stable-Baselines3, CleanRL and RLlib write it).
This writes a run's scalars there, live from the bus (`watch`) or afterwards from its journal
(`export`), into LOGDIR/<run>/ (one TensorBoard run per derl run), with the writer of
`torch.utils.tensorboard`, which needs the ``tensorboard`` package: ``pip install
'derl[tensorboard]'``, the way Stable-Baselines3 makes it optional.

Tags, and the step each is plotted against (`TAGS`):

- ``birth/fitness``, ``birth/cost_of_work``, ``birth/generation``: one point per birth, at its
  birth index (0 first); ``birth/steps_to_criterion``: env steps the body's learning curve took
  to reach the learning criterion of `derl report` (the 75th percentile of the initial
  population's fitness), written once the initial population is born; a body that never
  reaches it has no point, nor one whose report the watcher did not hear.
- ``run/born``, ``run/best_fitness``, ``run/failed``, ``run/evaluated``, ``run/steps_per_s``:
  the run's progress, at step births + evaluations done (during evolution, the births). Live,
  from the coordinator's status (every second; written at each new step and every `PROGRESS_S`
  within one, TensorBoard keeping the last point of a step); from a journal, at every birth,
  failure and evaluation, steps/s then being the sum of the rates of the trainings running at
  that moment (each accepted report's end, duration and rate; evaluations carry no rate).

Wall times are the real ones (TensorBoard's RELATIVE and WALL axes show the run's time; births
a late watcher asks the coordinator for get the time they were heard). TensorBoard drops every
point at or after a step that goes back, so each tag's steps only grow: births are written in
birth order, and a watcher started again in the same directory goes on after the last step
written there.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import zenoh

from derl.messages import (
    Birth,
    ChildFailed,
    Curve,
    EvalResult,
    FitnessReport,
    KeySpace,
    MessageBase,
    RunStatus,
)
from derl.metrics import EVENTS, TensorBoardRun
from derl.metrics import NoTensorBoard as NoTensorBoard
from derl.metrics import require_extra as require_extra
from derl.nodes.journal.history import RunHistory
from derl.nodes.runtime.bus import ZenohOptions, open_session
from derl.nodes.tools.logs import LogError, read_log
from derl.nodes.tools.topic import Checker, Tap, ask, choose_run

log = logging.getLogger("derl.tensorboard")

TAGS = {
    "birth/fitness": "fitness of each birth (step: birth index)",
    "birth/cost_of_work": "cost of work of each birth (step: birth index)",
    "birth/generation": "generation of each birth (step: birth index)",
    "birth/steps_to_criterion": "env steps to the learning criterion (step: birth index)",
    "run/born": "bodies born (step: births + evaluations)",
    "run/best_fitness": "best fitness so far (step: births + evaluations)",
    "run/failed": "children given up (step: births + evaluations)",
    "run/evaluated": "evaluations done (step: births + evaluations)",
    "run/steps_per_s": "env steps per second of all workers (step: births + evaluations)",
}
"""Every tag written, with what it is."""
FOLD_S = 0.5
"""How often a watcher writes what it heard."""
PROGRESS_S = 10.0
"""How often a watcher writes the run's status while its step stays (TensorBoard shows the last
point of a step: the file need not hold one a second)."""
GAP_S = 5.0
"""How long a watcher waits for a missing birth (asking the coordinator once) before going on."""


class Scalars:
    """A run's scalars (the tags of `TAGS`) into one TensorBoard run, each tag's steps only
    growing."""

    def __init__(self, board: TensorBoardRun) -> None:
        from derl.analysis.config import AnalysisConfig

        self.board = board
        self.percentile = AnalysisConfig().criterion_percentile
        self.initial: list[float] = []
        self.criterion: float | None = None
        self._waiting: list[tuple[Birth, FitnessReport | None, float]] = []

    def birth(self, birth: Birth, report: FitnessReport | None, wall: float) -> None:
        """A birth's points (`report`: the one it was born from, for its learning curve)."""
        step = birth.birth
        self.board.scalar("birth/fitness", birth.fitness, step, wall)
        self.board.scalar("birth/cost_of_work", birth.cost_of_work, step, wall)
        self.board.scalar("birth/generation", birth.generation, step, wall)
        if birth.parent is None:
            self.initial.append(birth.fitness)
        elif self.criterion is None:  # tournaments start once the initial population is born
            self.finish()
        if self.criterion is None:
            self._waiting.append((birth, report, wall))
        else:
            self._speed(birth, report, wall)

    def finish(self) -> None:
        """The initial population is complete: its criterion, and the births that waited."""
        from derl.analysis.learning import criterion_of

        if self.criterion is None and self.initial:
            self.criterion = criterion_of(self.initial, self.percentile)
        waiting, self._waiting = self._waiting, []
        for birth, report, wall in waiting:
            self._speed(birth, report, wall)

    def kept(self, curve: Curve) -> Curve:
        """What a birth's points need of its learning curve: all of it until the criterion is
        known, then only its first point at the criterion (none if it never gets there), so that
        a watcher of a long run keeps a number or two per birth (a 5M-step training's curve has
        1,220 points: about 80 kB in Python)."""
        if self.criterion is None:
            return curve
        level = self.criterion
        reached = next((k for k, value in enumerate(curve.returns) if value >= level), None)
        if reached is None:
            return Curve()
        return Curve(env_steps=(curve.env_steps[reached],), returns=(curve.returns[reached],))

    def _speed(self, birth: Birth, report: FitnessReport | None, wall: float) -> None:
        from derl.analysis.learning import first_reaching

        if report is None or self.criterion is None:
            return
        curve = report.curve
        steps = first_reaching(curve.env_steps, curve.returns, self.criterion)
        self.board.scalar("birth/steps_to_criterion", steps, birth.birth, wall)

    def progress(
        self,
        born: int,
        evaluated: int,
        best: float | None,
        failed: int,
        steps_per_s: float | None,
        wall: float,
    ) -> None:
        """The run's progress at step births + evaluations."""
        values = {"run/born": born, "run/best_fitness": best, "run/failed": failed,
                  "run/evaluated": evaluated, "run/steps_per_s": steps_per_s}  # fmt: skip
        for tag, value in values.items():
            self.board.scalar(tag, value, born + evaluated, wall, replace=True)


def _report(history: RunHistory, birth: Birth) -> FitnessReport | None:
    return history.reports.get(birth.agent)


# --- live ------------------------------------------------------------------------------------


class LiveRun:
    """What a watcher heard of a run, folded into `Scalars` every `FOLD_S`: births in birth
    order, each one fold after it came (its report, which comes by another path, is there by
    then; a missing birth is asked for once, then given up after `GAP_S`), the reports they were
    born from (without their policies, and once the criterion is known with only what their
    points need of their curves: `Scalars.kept`), and the latest status when its step changed or
    `PROGRESS_S` after the last one written."""

    def __init__(self, scalars: Scalars, ask_births: Callable[[], object]) -> None:
        self.scalars = scalars
        self.ask_births = ask_births
        self.history = RunHistory()
        self.pending: dict[int, tuple[Birth, float]] = {}
        self.next: int | None = None  # the birth index to write next
        self.gap_since: float | None = None
        self.progress_step, self.progress_at = -1, 0.0  # the run's progress last written
        self.done = False

    def fold(self, heard: Iterable[tuple[float, MessageBase]], now: float) -> None:
        status: tuple[RunStatus, float] | None = None
        births: list[tuple[Birth, float]] = []
        for wall, message in heard:
            if isinstance(message, FitnessReport):
                kept = {"checkpoint": b"", "curve": self.scalars.kept(message.curve)}
                self.history.apply(message.model_copy(update=kept))
            elif isinstance(message, Birth):
                births.append((message, wall))
            elif isinstance(message, ChildFailed):
                self.history.apply(message)
            elif isinstance(message, RunStatus):
                status = (message, wall)
        self._births(now)  # those of the folds before
        for birth, wall in births:
            if birth.agent not in self.history.born:
                self.pending.setdefault(birth.birth, (birth, wall))
        if status is not None:
            s, wall = status
            step = s.born + s.evaluated
            if step != self.progress_step or now - self.progress_at >= PROGRESS_S or s.done:
                self.scalars.progress(s.born, s.evaluated, s.best_fitness, s.failed,
                                      s.steps_per_s, wall)  # fmt: skip
                self.progress_step, self.progress_at = step, now
            self.done = s.done
            if s.done:
                self._births(math.inf)  # nothing more will come
                self.scalars.finish()

    def _births(self, now: float) -> None:
        while self.pending:
            first = min(self.pending)
            if self.next is not None and first > self.next:  # a birth went by unheard
                if self.gap_since is None:
                    self.gap_since = now
                    self.ask_births()
                    continue
                if now - self.gap_since < GAP_S:
                    return
                log.warning("births %d to %d not heard; going on", self.next, first - 1)
            birth, wall = self.pending.pop(first)
            self.gap_since = None
            self.next = first + 1
            self.history.apply(birth)
            self.scalars.birth(birth, _report(self.history, birth), wall)


def watch(
    options: ZenohOptions,
    run: str | None,
    logdir: Path,
    stop: threading.Event,
    started: Callable[[str, Path], None] = lambda run, path: None,
) -> Path:
    """Write run `run`'s scalars (or the only run's on the bus) into LOGDIR/<run> until `stop`
    or the run is done; `started(run, directory)` once it writes. The directory."""
    heard: deque[tuple[float, MessageBase]] = deque()
    with open_session(options) as session:
        run = choose_run(session, run)
        checker = Checker(session)

        def on_sample(sample: zenoh.Sample, _: float) -> None:
            message = checker.check(str(sample.key_expr), sample.payload.to_bytes())
            if message is not None:
                heard.append((time.time(), message))

        keys = KeySpace(run)
        taps = [Tap(session, keys.all(kind), on_sample) for kind in ("births", "fitness", "status")]
        directory = logdir / run
        board = TensorBoardRun(directory)
        live = LiveRun(Scalars(board), lambda: ask(session, keys.all("births"), on_sample))
        try:
            live.ask_births()  # the births before we came
            started(run, directory)
            while not live.done and not stop.wait(FOLD_S):
                live.fold(_drain(heard), time.monotonic())
                board.flush()
        finally:
            board.close()
    for tap in taps:
        tap.join()
    return directory


def _drain(heard: deque[tuple[float, MessageBase]]) -> list[tuple[float, MessageBase]]:
    taken = []
    while heard:
        taken.append(heard.popleft())
    return taken


# --- from a journal ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Training:
    """When an accepted training ran and how fast (from its report and the time it came)."""

    start: float
    end: float
    steps_per_s: float


def export(source: Path, logdir: Path) -> Path:
    """Write the scalars of the run in `source` (a run directory or an MCAP log) into a new
    LOGDIR/<run>; the directory."""
    history = RunHistory()
    events: list[tuple[float, MessageBase]] = []
    reports: dict[str, float] = {}  # job -> when its report came
    for logged in read_log(source):
        message, wall = logged.message, logged.log_time / 1e9
        before = (len(history.births), len(history.failed), len(history.evaluations))
        history.apply(message)
        if isinstance(message, FitnessReport):
            reports[message.job] = wall
        if (len(history.births), len(history.failed), len(history.evaluations)) != before:
            events.append((wall, message))
    if history.run is None:
        raise LogError(f"{source} holds no message of a run")
    directory = logdir / history.run
    if directory.exists() and any(directory.glob(EVENTS)):
        raise FileExistsError(f"{directory} holds event files already; choose another LOGDIR")
    trainings = _trainings(history, reports)
    starts = [t.start for t in trainings]
    board = TensorBoardRun(directory)
    try:
        scalars = Scalars(board)
        born = failed = evaluated = 0
        best: float | None = None
        for wall, message in events:
            if isinstance(message, Birth):
                scalars.birth(message, _report(history, message), wall)
                born += 1
                best = message.fitness if best is None else max(best, message.fitness)
            elif isinstance(message, ChildFailed):
                failed += 1
            elif isinstance(message, EvalResult):
                evaluated += 1
            rate = sum(t.steps_per_s for t in trainings[: bisect.bisect_right(starts, wall)]
                       if t.end >= wall)  # fmt: skip
            scalars.progress(born, evaluated, best, failed, rate, wall)
        scalars.finish()
    finally:
        board.close()
    return directory


def _trainings(history: RunHistory, reports: dict[str, float]) -> list[Training]:
    """The accepted trainings (of the children born), by start time."""
    runs = []
    for birth in history.births:
        report = history.reports.get(birth.agent)
        if birth.repeat_of is None and report is not None and report.job in reports:
            end = reports[report.job]
            runs.append(Training(end - report.wall_s, end, report.steps_per_s))
    return sorted(runs, key=lambda t: t.start)
