"""The trained-agent folder: one body with its controller, as `derl train` leaves it and as a
run's ``best/NN-<agent>/`` holds it; the one place that names its files, writes and reads them.

Both kinds hold (`derl train` from its start, a run's ``best/`` at the run's end):

- ``genome.json``: the body (`Genome`); ``body.xml``: its MJCF, for MuJoCo's viewer;
- ``training.json``: its task and PPO settings (`TrainingSettings`; `derl train`'s TensorBoard
  folder too);
- ``checkpoint.pt``: the policy (`derl.rl.checkpoint`).

`derl train` adds, at every save:

- ``result.json``: the settings and the `LifetimeResult` so far, the iterations done, whether it
  finished (a value that is no number, e.g. a cost of work, is null: strict JSON);
- ``curve.csv``, ``curve.png``: each iteration's record (`derl.metrics`), the return over steps;
- ``training-state.pt``: the training's whole state, to resume a stopped training or extend a
  finished one.

A folder `derl train` wrote before ``training.json`` existed names its task and settings in
``result.json`` (``config``): it is read all the same. Every file is written whole or not at all
(`derl.files.write_atomic`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import AliasChoices, BaseModel, ConfigDict, Field, ValidationError

from derl.files import write_atomic
from derl.rl.config import PPOConfig

if TYPE_CHECKING:
    from derl.lifetime import LifetimeResult
    from derl.metrics import Record
    from derl.unimal import Genome

GENOME, BODY, CHECKPOINT = "genome.json", "body.xml", "checkpoint.pt"
SETTINGS, RESULT, STATE = "training.json", "result.json", "training-state.pt"
CURVE_CSV, CURVE_PNG = "curve.csv", "curve.png"
TASK_FILES = (SETTINGS, RESULT)
"""The JSON files that name a folder's task (no body is in them)."""


class NotTrained(ValueError):
    """A folder that does not hold what a replay or a resume needs."""


class TrainingSettings(BaseModel):
    """``training.json``: what the body learnt in, and how (read back from a folder derl wrote:
    other keys, e.g. those of an older ``result.json``, are ignored)."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    task: str
    ppo: PPOConfig = Field(validation_alias=AliasChoices("ppo", "config"))
    tensorboard: Path | None = None
    """`derl train --tensorboard`'s LOGDIR (absolute), which a resume writes to again."""


class Progressed(BaseModel):
    """What ``result.json`` says of the training's progress."""

    model_config = ConfigDict(extra="ignore", frozen=True)

    iterations: int = 0
    finished: bool = True  # the shipped agents' files predate the key: finished trainings
    env_steps: int = 0


@dataclass(frozen=True)
class AgentFolder:
    """The trained-agent folder at `path`."""

    path: Path

    def file(self, name: str) -> Path:
        return self.path / name

    # --- writing ----------------------------------------------------------------------------

    def write_body(self, genome: Genome) -> None:
        from derl.unimal import to_mjcf

        write_atomic(self.file(GENOME), genome.model_dump_json(indent=2) + "\n")
        write_atomic(self.file(BODY), to_mjcf(genome))

    def write_settings(self, settings: TrainingSettings) -> None:
        text = settings.model_dump_json(indent=2, exclude_none=True)
        write_atomic(self.file(SETTINGS), text + "\n")

    def write_checkpoint(self, data: bytes) -> None:
        write_atomic(self.file(CHECKPOINT), data)

    def write_result(
        self, config: PPOConfig, summary: LifetimeResult, iterations: int, finished: bool
    ) -> None:
        """``result.json``: the settings, the summary, the iterations done, whether the training
        finished; a value that is no number (a cost of work where the body never moved forward)
        is null."""
        record = {"config": config.model_dump(), **summary.model_dump(),
                  "iterations": iterations, "finished": finished}  # fmt: skip
        write_atomic(self.file(RESULT), json.dumps(_finite(record), indent=2) + "\n")

    def write_curve(self, records: Iterable[Record], task: str) -> None:
        """``curve.csv`` (a row per iteration: `derl.metrics.write_csv`) and ``curve.png``."""
        from derl.metrics import plot_return, write_csv

        records = list(records)
        write_csv(self.file(CURVE_CSV), records)
        plot_return(self.file(CURVE_PNG), records, task)

    def write_state(self, data: bytes) -> None:
        write_atomic(self.file(STATE), data)

    def remove_state(self) -> None:
        self.file(STATE).unlink(missing_ok=True)

    # --- reading ----------------------------------------------------------------------------

    def state(self) -> bytes | None:
        """The training state saved here, if any."""
        path = self.file(STATE)
        return path.read_bytes() if path.is_file() else None

    def holds_training(self) -> bool:
        """Whether `derl train` began a training here."""
        return any(self.file(name).is_file() for name in (*TASK_FILES, STATE))

    def settings(self) -> TrainingSettings:
        """The task and settings (`NotTrained` where no file names them or one is unreadable)."""
        named = next((self.file(n) for n in TASK_FILES if self.file(n).is_file()), None)
        if named is None:
            raise NotTrained(f"{self.path} holds no {' or '.join(TASK_FILES)}")
        try:
            return TrainingSettings.model_validate_json(named.read_text())
        except (OSError, ValidationError) as error:
            raise NotTrained(f"{named}: cannot read it: {error}") from None

    def task(self) -> str:
        """The task the body learnt (all a replay needs of the settings)."""
        named = next((self.file(n) for n in TASK_FILES if self.file(n).is_file()), None)
        if named is None:
            raise NotTrained(f"{self.path} holds no {' or '.join(TASK_FILES)}")
        try:
            task = json.loads(named.read_text())["task"]
        except (OSError, ValueError, KeyError) as error:
            raise NotTrained(f"{named}: cannot read its task: {error}") from None
        if not isinstance(task, str):
            raise NotTrained(f"{named}: its task is not a name")
        return task

    def progressed(self) -> Progressed | None:
        """What ``result.json`` says of the progress (None before the first save)."""
        path = self.file(RESULT)
        if not path.is_file():
            return None
        try:
            return Progressed.model_validate_json(path.read_text())
        except (OSError, ValidationError) as error:
            raise NotTrained(f"{path}: cannot read it: {error}") from None

    def genome(self) -> Genome:
        from derl.unimal import Genome

        try:
            return Genome.model_validate_json(self.file(GENOME).read_text())
        except (OSError, ValidationError) as error:
            raise NotTrained(f"{self.file(GENOME)}: cannot read it: {error}") from None

    def checkpoint(self) -> bytes:
        return self.file(CHECKPOINT).read_bytes()

    def missing(self) -> list[str]:
        """What a replay needs that the folder lacks."""
        missing = [name for name in (GENOME, CHECKPOINT) if not self.file(name).is_file()]
        if not any(self.file(name).is_file() for name in TASK_FILES):
            missing.append(" or ".join(TASK_FILES))
        return missing


def _finite(value: Any) -> Any:
    """`value` with every float that is no finite number as None (strict JSON has no NaN)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value
