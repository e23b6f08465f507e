"""One metrics path: each PPO iteration's `Progress` becomes one record (`record`), and writers
take the records: the CSV file (`write_csv`), TensorBoard (`TensorBoardRun.write`), the live line
of `derl train`. Stable-Baselines3's ``logger.record()`` feeding its CSV and TensorBoard writers
is the shape. The diagnostics' names are `derl.rl.ppo.Diagnostics`' fields (`columns`).

TensorBoard's writer lives here too, for anything that writes scalars (`derl tensorboard` and
`derl export --tensorboard` of a run as well): `TensorBoardRun` writes a point only where its
value is a number and its tag's step grows (TensorBoard drops every point at or after a step
that goes back), going on after the last step already written in its folder. It needs the
``tensorboard`` package, an extra: ``pip install 'derl[tensorboard]'``.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import importlib.util
import io
import math
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from derl.files import write_atomic

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

    from derl.rl.ppo import Progress

Record = dict[str, float | None]
"""One iteration's values by name (`columns`); None where a value is not defined yet."""

HEAD = ("iteration", "env_steps", "mean_return", "ep_rew_mean", "ep_len_mean", "episodes")
TAIL = ("steps_per_s",)
SB3_TAGS = {
    "iteration": "time/iterations",
    "mean_return": "rollout/fitness_term_mean",
    "ep_rew_mean": "rollout/ep_rew_mean",
    "ep_len_mean": "rollout/ep_len_mean",
    "episodes": "rollout/episodes",
    "steps_per_s": "time/fps",
}
"""The TensorBoard tag of each record name outside the diagnostics (each diagnostic D is
``train/D``), at the step env_steps, Stable-Baselines3's names where it has one."""
EXTRA = "pip install 'derl[tensorboard]'"
EVENTS = "events.out.tfevents.*"


@functools.cache
def diagnostics() -> tuple[str, ...]:
    """The names of `derl.rl.ppo.Diagnostics`' fields."""
    from derl.rl.ppo import Diagnostics

    return tuple(field.name for field in dataclasses.fields(Diagnostics))


def columns() -> tuple[str, ...]:
    """Every record's names, in the CSV's order: the iteration's, the diagnostics, the speed."""
    return (*HEAD, *diagnostics(), *TAIL)


def tags() -> dict[str, str]:
    """Record name -> TensorBoard tag (env_steps is the step, not a tag)."""
    return {**SB3_TAGS, **{name: f"train/{name}" for name in diagnostics()}}


def record(progress: Progress) -> Record:
    """One iteration's record."""
    values: Record = {
        "iteration": progress.iteration,
        "env_steps": progress.env_steps,
        "mean_return": progress.recent_return,
        "ep_rew_mean": progress.episode_return,
        "ep_len_mean": progress.episode_length,
        "episodes": progress.episodes,
        "steps_per_s": progress.steps_per_second,
    }
    measured = progress.diagnostics
    for name in diagnostics():
        values[name] = None if measured is None else getattr(measured, name)
    return values


def write_csv(path: Path, records: Iterable[Mapping[str, float | None]]) -> None:
    """A row per record, with a header of `columns` (an undefined value blank)."""
    text = io.StringIO()
    writer = csv.writer(text)
    names = columns()
    writer.writerow(names)
    for values in records:
        writer.writerow(["" if values[name] is None else values[name] for name in names])
    write_atomic(path, text.getvalue())


def plot_return(path: Path, records: Iterable[Mapping[str, float | None]], task: str) -> None:
    """The mean return over env steps, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [(r["env_steps"], r["mean_return"]) for r in records if r["mean_return"] is not None]
    figure, axis = plt.subplots(figsize=(6, 3.5))
    if shown:
        axis.plot(*zip(*shown, strict=True))
    axis.set(xlabel="environment steps", ylabel="mean episode return (fitness term)", title=task)
    axis.grid(alpha=0.3)
    figure.tight_layout()
    image = io.BytesIO()
    figure.savefig(image, format="png", dpi=120)
    plt.close(figure)
    write_atomic(path, image.getvalue())


class NoTensorBoard(ImportError):
    """The `tensorboard` package (derl's extra) is not installed."""


def require_extra() -> None:
    """NoTensorBoard, saying how to install it, unless the `tensorboard` package is there."""
    if importlib.util.find_spec("tensorboard") is None:
        raise NoTensorBoard(f"TensorBoard is an extra: {EXTRA}")


def summary_writer() -> type[SummaryWriter]:
    """torch's SummaryWriter (NoTensorBoard without the extra)."""
    require_extra()
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter


def last_steps(folder: Path) -> dict[str, int]:
    """The last step of each tag in the event files already in `folder`."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    last: dict[str, int] = {}
    for path in sorted(folder.glob(EVENTS)):
        for event in EventFileLoader(str(path)).Load():
            for value in event.summary.value:
                last[value.tag] = max(last.get(value.tag, -1), event.step)
    return last


class TensorBoardRun:
    """One TensorBoard run: the event files of `folder` (made if missing; NoTensorBoard without
    the extra, OSError where it cannot be made), each tag's steps only growing."""

    def __init__(self, folder: Path) -> None:
        writer = summary_writer()
        self.written = last_steps(folder) if folder.is_dir() else {}
        """Tag -> the last step written (in this folder, by anyone)."""
        folder.mkdir(parents=True, exist_ok=True)
        self.writer = writer(str(folder))

    def scalar(
        self, tag: str, value: float | None, step: int, wall: float, replace: bool = False
    ) -> None:
        """One point, unless it is undefined or its step goes back (or stays, unless it
        `replace`s the last)."""
        last = self.written.get(tag, -1)
        back = step < last or (step == last and not replace)
        if value is None or not math.isfinite(value) or back:
            return
        self.writer.add_scalar(tag, value, step, walltime=wall)
        self.written[tag] = step

    def write(self, values: Mapping[str, float | None]) -> None:
        """A training's record, at its env steps (`tags`)."""
        now, step = time.time(), values["env_steps"]
        assert step is not None  # always counted
        for name, tag in tags().items():
            self.scalar(tag, values[name], int(step), now)

    def flush(self) -> None:
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()
