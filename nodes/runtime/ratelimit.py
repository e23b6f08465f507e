"""Repeated warnings, rate-limited: the first few of a kind per interval, then a line with a count.

A flood of junk on the bus makes every node and tool warn once per rejected sample; a full disk
makes the coordinator complain once per report re-sent. `RepeatedWarnings` is a logging filter
for the handler that prints a process's log (every `derl` command installs it, `nodes.cli.main`):
records of level WARNING and above with the same logger and message template (the format string,
not its arguments: `rejected (%s) %s: %s` is one kind) pass `burst` at a time per `interval_s`;
the rest are counted, and when the interval is over one line says how many were not shown and
gives the last of them. Lower levels pass untouched (the coordinator's births line is a line a
second on purpose), except records logged with ``extra=FLOOD``: INFO lines that a sender can
repeat at will (a duplicate report acknowledged again). The count of an interval is written by a
timer thread when the interval ends, or when the process exits.
"""

from __future__ import annotations

import atexit
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

BURST = 5
INTERVAL_S = 10.0
FLOOD = {"flood": True}
"""``extra`` of a record below WARNING that is rate-limited all the same."""

Kind = tuple[str, int, object]  # logger, level, message template


@dataclass
class _Window:
    end: float  # when this interval ends (monotonic s)
    shown: int = 1
    hidden: int = 0
    last: str = ""  # the last record not shown, formatted


class RepeatedWarnings(logging.Filter):
    def __init__(
        self,
        burst: int = BURST,
        interval_s: float = INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__()
        self.burst, self.interval_s, self.clock = burst, interval_s, clock
        self._windows: dict[Kind, _Window] = {}
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._timer: threading.Thread | None = None
        atexit.register(self.flush)

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "count_of_repeats", False) or (
            record.levelno < logging.WARNING and not getattr(record, "flood", False)
        ):
            return True
        kind: Kind = (record.name, record.levelno, record.msg)
        now = self.clock()
        with self._lock:
            window = self._windows.get(kind)
            if window is not None and now < window.end:
                if window.shown < self.burst:
                    window.shown += 1
                    return True
                window.hidden += 1
                window.last = record.getMessage()
                self._start_timer()
                return False
            self._windows[kind] = _Window(end=now + self.interval_s)
        if window is not None:
            self._say(kind, window)  # an interval whose count the timer has not written yet
        return True

    def flush(self) -> None:
        """Write the count of every interval with records not shown, over or not."""
        self._say_over(float("inf"))

    def _start_timer(self) -> None:
        if self._timer is None:
            self._timer = threading.Thread(target=self._run, name="repeated-warnings", daemon=True)
            self._timer.start()
        self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._lock:
                ends = [w.end for w in self._windows.values() if w.hidden]
                wait = min(ends) - self.clock() if ends else None
                if wait is None or wait > 0:
                    self._wake.wait(wait)
                    continue
            self._say_over(self.clock())

    def _say_over(self, now: float) -> None:
        """Write the count of every interval that ended before `now` with records not shown."""
        with self._lock:
            over = [(k, w) for k, w in self._windows.items() if w.hidden and w.end <= now]
            for kind, _ in over:
                del self._windows[kind]
        for kind, window in over:
            self._say(kind, window)

    def _say(self, kind: Kind, window: _Window) -> None:
        if not window.hidden:
            return
        name, level, _ = kind
        logging.getLogger(name).log(
            level,
            "... and %d more like it in %g s, not shown (the last: %s)",
            window.hidden,
            self.interval_s,
            window.last,
            extra={"count_of_repeats": True},
        )


def install(handler: logging.Handler) -> logging.Handler:
    """`handler`, its repeated warnings rate-limited."""
    handler.addFilter(RepeatedWarnings())
    return handler
