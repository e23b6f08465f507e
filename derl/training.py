"""`derl train`'s work, with no command line: one body's training into its agent folder
(`derl.agent_folder`), begun new (`begin`), resumed where it was stopped or extended past the end
of a finished one (`resume`), then run (`run`).

A training saves what resuming needs every `every` iterations, when it is stopped and at its end:
the state first, then the policy, the curve and the result (each file whole or not at all, the
result last), so that a folder always resumes from its newest state. `Stop` is how signals stop
it: the first SIGINT or SIGTERM (Slurm's preemption) at the end of an iteration, once it is
saved; a second one at once (`KeyboardInterrupt`), though never in the middle of a save. A
resumed training ends with the bits of one never stopped; an extension (a larger budget) goes on
from the finished training's last state, its learning rate decaying linearly from
lr x (1 - steps done / new budget) to 0 at its new end, as Stable-Baselines3's
``learn(..., reset_num_timesteps=False)`` does: the same extension gives the same bits every time.
Each iteration's record (`derl.metrics`) goes to TensorBoard, if asked, and to the caller's
display, and at every save to ``curve.csv``.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import BaseModel, ConfigDict, Field

from derl.agent_folder import CHECKPOINT, STATE, AgentFolder, NotTrained, TrainingSettings
from derl.metrics import NoTensorBoard, Record, TensorBoardRun, record
from derl.rl.config import PPOConfig, PPOHyperparameters

if TYPE_CHECKING:
    from derl.lifetime import LifetimeResult
    from derl.rl.ppo import Progress, TrainResult
    from derl.unimal import Genome


class TrainingError(Exception):
    """What keeps a training from beginning or going on."""


class Taken(TrainingError):
    """The folder holds a training already, or a trained agent (`held`: "a finished training",
    "a stopped training", "a trained agent": a run's best/ folder): a new training would
    overwrite it."""

    def __init__(self, folder: Path, held: str) -> None:
        super().__init__(f"{folder} holds {held}")
        self.folder, self.held = folder, held


class NothingToResume(TrainingError):
    """The folder holds no training that can go on (with the budget asked for)."""


class Finished(NothingToResume):
    """The folder's training finished: only a larger budget goes on with it."""


class NoBoard(TrainingError):
    """TensorBoard cannot be written where asked (its extra missing, a folder not writable)."""


class TrainingChanges(BaseModel):
    """What a new training changes of the paper's PPO: `derl train --settings FILE.yaml` and its
    `--set ppo.KEY=VALUE`s (the keys of a profile's ``ppo``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    ppo: PPOHyperparameters = Field(default_factory=PPOHyperparameters)


@dataclass(frozen=True)
class Plan:
    """What one training trains, where, and what it goes on from."""

    folder: AgentFolder
    genome: Genome
    settings: TrainingSettings
    state: bytes | None = None
    """The state it goes on from (None: from the beginning)."""

    @property
    def config(self) -> PPOConfig:
        return self.settings.ppo

    @property
    def board(self) -> Path | None:
        """The TensorBoard run's folder: LOGDIR/<the agent folder's name>."""
        logdir = self.settings.tensorboard
        return None if logdir is None else logdir / self.folder.path.resolve().name


def begin(
    genome: Genome, task: str, config: PPOConfig, out: Path, tensorboard: Path | None
) -> Plan:
    """A new training into `out`; `Taken` where `out` holds one already."""
    folder = AgentFolder(out)
    if folder.holds_training():
        raise Taken(out, _held(folder))
    logdir = None if tensorboard is None else tensorboard.resolve()
    return Plan(folder, genome, TrainingSettings(task=task, ppo=config, tensorboard=logdir))


def resume(out: Path, steps: int | None = None, tensorboard: Path | None = None) -> Plan:
    """The training of `out`, to go on with: a stopped one to its budget, or to `steps` (a
    larger budget: a finished one is extended); TensorBoard where it wrote before unless
    `tensorboard` says where. `NothingToResume` says why there is none."""
    from pydantic import ValidationError

    from derl.lifetime import with_budget

    folder = AgentFolder(out)
    if not folder.holds_training():
        raise NothingToResume(f"{out}: no training there")
    if _held(folder) == AGENT:
        raise NothingToResume(f"{out} holds {AGENT}, not a training `derl train` began")
    try:
        settings, progressed = folder.settings(), folder.progressed()
        genome, state = folder.genome(), folder.state()
    except NotTrained as error:
        raise NothingToResume(f"cannot read the training it holds: {error}") from None
    done = 0 if progressed is None else progressed.env_steps
    finished = progressed is not None and progressed.finished
    config = settings.ppo
    if steps is not None:
        try:
            config = with_budget(config, steps)
        except ValidationError:
            raise NothingToResume(f"{steps:,} env steps are less than one rollout") from None
        if config.iterations * config.batch_size <= done and finished:
            raise NothingToResume(f"{steps:,} env steps are no more than the {done:,} done")
        if progressed is not None and config.iterations < progressed.iterations:
            raise NothingToResume(f"{steps:,} env steps are fewer than the {done:,} done")
    elif finished:
        raise Finished(f"its training finished ({done:,} env steps)")
    if finished and state is None:
        raise NothingToResume(f"its training finished ({done:,} env steps) without the state "
                              "an extension goes on from")  # fmt: skip
    logdir = settings.tensorboard if tensorboard is None else tensorboard.resolve()
    settings = settings.model_copy(update={"ppo": config, "tensorboard": logdir})
    return Plan(folder, genome, settings, state)


AGENT = "a trained agent"


def _held(folder: AgentFolder) -> str:
    """What a folder that holds a training or an agent holds: a run's best/ folder has a
    policy and no result; a training stopped before its first save has neither."""
    progressed = folder.progressed()
    if progressed is None and not folder.file(STATE).is_file():
        return AGENT if folder.file(CHECKPOINT).is_file() else "a stopped training"
    return "a finished training" if progressed and progressed.finished else "a stopped training"


def open_board(plan: Plan) -> TensorBoardRun | None:
    """The plan's TensorBoard run (`NoBoard` says why it cannot be written), or None."""
    if plan.board is None:
        return None
    try:
        return TensorBoardRun(plan.board)
    except NoTensorBoard as error:
        raise NoBoard(str(error)) from None
    except OSError as error:
        raise NoBoard(f"cannot make {plan.board}: {error.strerror or error}") from None


class Stop:
    """How signals stop a training: the first SIGINT or SIGTERM sets `event` (the training saves
    and stops at the end of its iteration), a second one raises `KeyboardInterrupt` (stop at
    once), unless it comes while the training saves (`saving`): the save is finished, and the
    training stops right after it. `notice` gets a line to show for each."""

    def __init__(self, notice: Callable[[str], None]) -> None:
        self.event = threading.Event()
        self.notice = notice
        self._saving = False

    def install(self) -> None:
        for number in (signal.SIGINT, signal.SIGTERM):
            signal.signal(number, self._handle)

    def _handle(self, number: int, _frame: object) -> None:
        name = signal.Signals(number).name
        if not self.event.is_set():
            self.event.set()
            self.notice(f"{name}: saving at the end of this iteration, then stopping (again: "
                        "stop at once)")  # fmt: skip
        elif self._saving:
            self.notice(f"{name}: stopping once this save is written")
        else:
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def saving(self) -> Iterator[None]:
        self._saving = True
        try:
            yield
        finally:
            self._saving = False


@dataclass(frozen=True)
class Outcome:
    """What `run` did: the summary and the result so far, and whether the training finished."""

    summary: LifetimeResult
    result: TrainResult
    finished: bool


def run(
    plan: Plan,
    display: Callable[[Record], None],
    stop: Stop,
    board: TensorBoardRun | None = None,
    every: int = 0,
    nthread: int = 1,
) -> Outcome:
    """Train as `plan` says into its folder (made before), `display`ing each iteration's record
    (and writing it to `board`), saving every `every` iterations (0: only when stopped and at
    the end); `NothingToResume` where the state is not one of the plan's settings."""
    from derl.lifetime import learn

    folder, config = plan.folder, plan.config
    folder.write_body(plan.genome)
    folder.write_settings(plan.settings)
    saved_at = -1

    def shown(progress: Progress) -> None:
        values = record(progress)
        if board is not None:
            board.write(values)
        display(values)

    def save(summary: LifetimeResult, result: TrainResult, state: bytes | None) -> None:
        nonlocal saved_at
        with stop.saving():
            if state is None:
                folder.remove_state()
            else:
                folder.write_state(state)
            folder.write_checkpoint(result.checkpoint.to_bytes())
            folder.write_curve([record(point) for point in result.progress], summary.task)
            finished = result.iterations == config.iterations
            folder.write_result(config, summary, result.iterations, finished)
            saved_at = result.iterations

    try:
        summary, result = learn(
            plan.genome, plan.settings.task, config, shown, nthread=nthread, save=save,
            every=every, stop=stop.event, resume=plan.state, last=True,
        )  # fmt: skip
    except ValueError as error:  # a state of another derl or configuration
        if plan.state is None:
            raise
        raise NothingToResume(str(error)) from None
    finished = result.iterations == config.iterations
    if finished and saved_at != result.iterations:  # its end could not be captured: no state
        save(summary, result, None)
    return Outcome(summary, result, finished)
