"""What a long command shows while it works: a rich progress bar on a terminal; in a file (nohup,
Slurm, `| tee`) a plain timestamped line every `EVERY_S` seconds, which rich's bar would not
print until the end, and lines that are not wrapped at rich's 80 columns."""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from datetime import datetime
from types import TracebackType
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

EVERY_S = 10.0
"""Seconds between two progress lines in a file."""


def output_console() -> Console:
    """The console of a command's output: on a terminal rich's own; else lines are not wrapped
    (a path stays whole in a log file) and carry no colour codes."""
    if sys.stdout.isatty():
        return Console()
    return Console(soft_wrap=True, highlight=False)


def clock(seconds: float) -> str:
    """H:MM:SS, as rich's bar shows elapsed and remaining time."""
    whole = int(seconds)
    return f"{whole // 3600}:{whole // 60 % 60:02d}:{whole % 60:02d}"


class Shown:
    """One task's progress, `update`d as it goes: on a terminal a rich bar of `columns` (after
    the description and a bar, before elapsed and remaining time); in a file, every `every_s`
    seconds and at the end, the time, `line(state)` (`state`: the task's fields, with
    "description", "completed" and "total") and elapsed and remaining time."""

    def __init__(
        self,
        console: Console,
        description: str,
        total: float,
        columns: tuple[TextColumn, ...],
        line: Callable[[dict[str, Any]], str],
        every_s: float = EVERY_S,
        **fields: Any,
    ) -> None:
        self.console, self.line, self.every_s = console, line, every_s
        self.state: dict[str, Any] = {
            "description": description,
            "completed": 0,
            "total": total,
            **fields,
        }
        self.bar: Progress | None = None
        if console.is_terminal:
            bar = (TextColumn("[bold]{task.description}"), BarColumn(), *columns)
            self.bar = Progress(*bar, TimeElapsedColumn(), TimeRemainingColumn(), console=console)
        self.start, self.printed = time.monotonic(), -math.inf  # the first update is shown
        self.rate_from: tuple[float, float] | None = None  # (time, completed) of the first update

    def __enter__(self) -> Shown:
        if self.bar is not None:
            self.bar.__enter__()
            fields = {k: v for k, v in self.state.items() if k not in ("completed", "total")}
            self.task = self.bar.add_task(total=self.state["total"], **fields)
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        if self.bar is not None:
            self.bar.__exit__(kind, error, trace)
        elif kind is None and self.rate_from is not None:
            self._print()  # where it ended

    def update(self, **fields: Any) -> None:
        """Set some of the task's fields; in a file, print a line when `every_s` have passed."""
        now = time.monotonic()
        if self.rate_from is None and "completed" in fields:
            self.rate_from = (now, float(fields["completed"]))
        self.state.update(fields)
        if self.bar is not None:
            self.bar.update(self.task, **fields)
        elif now - self.printed >= self.every_s:
            self.printed = now
            self._print()

    def _print(self) -> None:
        now = time.monotonic()
        stamp = datetime.now().strftime("%Y-%m-%d %H:%M:%S")
        done, total, left = float(self.state["completed"]), self.state["total"], "-"
        if self.rate_from is not None and done > self.rate_from[1] and total:
            rate = (done - self.rate_from[1]) / (now - self.rate_from[0])
            left = clock(max(0.0, (total - done) / rate))
        text = f"{stamp} {self.line(self.state)}, {clock(now - self.start)} elapsed, {left} left"
        self.console.print(text, markup=False, highlight=False, soft_wrap=True)
