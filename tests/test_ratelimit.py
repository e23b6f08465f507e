"""Repeated warnings rate-limited: the first few of a kind per interval, then one count, written
when the interval ends (by its timer) or before the next warning of the kind."""

from __future__ import annotations

import logging

from derl.nodes.runtime.ratelimit import FLOOD, RepeatedWarnings
from derl.nodes.testing.waiting import ManualClock, wait_until


class Kept(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"{record.levelname} {record.getMessage()}")


def test_a_flood_is_cut_to_a_burst_and_a_count_per_interval() -> None:
    """On a clock the test moves: the interval is over when it says so, however slowly the
    flood is logged; the timer thread sees that within the interval's length of real time."""
    kept, clock = Kept(), ManualClock()
    kept.addFilter(RepeatedWarnings(burst=2, interval_s=0.05, clock=clock))
    log = logging.getLogger("test.ratelimit")
    log.addHandler(kept)
    log.propagate = False
    log.setLevel(logging.INFO)
    try:
        for k in range(50):
            log.warning("rejected %d", k)
            log.info("born %d", k)  # below WARNING: never limited
            log.info("copy %d acknowledged", k, extra=FLOOD)  # ... unless a sender floods it
        log.error("another kind")
        clock.advance(0.05)  # the timer writes the count once the interval is over
        wait_until(lambda: sum("more like it" in line for line in kept.lines) == 2, 10,
                   "the counts of the interval's warnings and floods")  # fmt: skip
        assert kept.lines[:6] == ["WARNING rejected 0", "INFO born 0", "INFO copy 0 acknowledged",
                                  "WARNING rejected 1", "INFO born 1",
                                  "INFO copy 1 acknowledged"]  # fmt: skip
        assert sum(line.startswith("INFO born") for line in kept.lines) == 50
        assert sum(line.startswith("INFO copy") for line in kept.lines) == 2
        assert "ERROR another kind" in kept.lines
        assert (
            "WARNING ... and 48 more like it in 0.05 s, not shown (the last: rejected 49)"
            in kept.lines[-2:]
        )
        log.warning("rejected %d", 50)  # a new interval
        assert kept.lines[-1] == "WARNING rejected 50"
    finally:
        log.removeHandler(kept)
