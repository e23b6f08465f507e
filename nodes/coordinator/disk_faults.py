"""What the coordinator could not write (a full disk, an I/O error), said once a minute.

A journal that cannot be written stalls the coordinator (`Ledger.stalled`) until it can; a
checkpoint file that cannot be written holds its Ack back until the trainer's re-sent report
writes it. Either is retried every second, and would be said every second: `DiskFaults` says
the first failure at once, which file and why, then at most one line a minute with how many
writes failed meanwhile, and one line when writing works again. Its methods are called from the
coordinator's loop and from the checkpoint writer's callbacks.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger("derl.coordinator")

SAY_EVERY_S = 60.0


class DiskFaults:
    def __init__(self, every_s: float = SAY_EVERY_S, clock: Callable[[], float] = time.monotonic):
        self.every_s, self.clock = every_s, clock
        self._lock = threading.Lock()
        self.since: float | None = None  # when writing first failed (None: it works)
        self._said = 0.0  # when it was last said
        self._failed = 0  # writes failed since then

    def failed(self, path: Path, error: BaseException, consequence: str) -> None:
        """A write of `path` failed with `error` (what follows: `consequence`)."""
        why = str(error)
        if isinstance(error, OSError) and error.errno:
            why = os.strerror(error.errno)
        now = self.clock()
        with self._lock:
            first = self.since is None
            if self.since is None:
                self.since = now
            self._failed += 1
            if not first and now - self._said < self.every_s:
                return
            failed, self._failed, self._said = self._failed, 0, now
            since = now - self.since
        if first:
            log.error("cannot write %s (%s): %s", path, why, consequence)
        else:
            log.error("still cannot write, for %.0f s: %s (%s): %s (%d writes failed in the last "
                      "%.0f s)", since, path, why, consequence, failed, self.every_s)  # fmt: skip

    def works(self, what: str) -> None:
        """A write worked again (`what` it did): said if writes had failed."""
        with self._lock:
            if self.since is None:
                return
            since, self.since, self._failed = self.clock() - self.since, None, 0
        log.warning("writing works again, after %.0f s: %s", since, what)
