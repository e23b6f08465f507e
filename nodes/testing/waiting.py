"""Waiting in tests and bench/ scripts without sleeping for luck: `wait_until` a condition holds,
failing with what was awaited at its deadline, and a `ManualClock` a test moves by hand for what
takes a clock (the coordinator, the workers, rate-limited warnings, disk faults)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

POLL_S = (0.01, 0.2)  # `wait_until` asks its condition again after the first, doubled up to
# the last: a quick condition is seen at once, a long wait (a run's births, read from its journal)
# costs the cores the nodes under test share little


class WaitTimeout(AssertionError):
    """What a test waited for did not happen in time."""


def wait_until(condition: Callable[[], T], timeout: float, what: str) -> T:
    """The first true value of `condition()`, asked until `timeout` seconds are over (`POLL_S`
    apart); then `WaitTimeout`, naming what was awaited."""
    deadline = time.monotonic() + timeout
    poll_s = POLL_S[0]
    while True:
        value = condition()
        if value:
            return value
        left = deadline - time.monotonic()
        if left <= 0:
            raise WaitTimeout(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(min(poll_s, left))
        poll_s = min(2 * poll_s, POLL_S[1])


class ManualClock:
    """A monotonic clock that stands still until the test moves it (`advance`): pass it where
    `time.monotonic` is the default."""

    def __init__(self, start: float = 0.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds
