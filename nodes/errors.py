"""What goes wrong for a user, as exceptions with the one line they read and an exit status.

Nothing below the command line exits the process: library code raises a `DerlError` whose
message is the whole reason, in one line. The command line (`derl.nodes.cli.main`) prints it as
``derl: <message>`` on stderr and exits with the error's `code`, in that one place. A supervisor
(`derl run`, `derl launch`, `derl study`) restarts a node that failed, but not one whose exit
status is `FINAL`: no restart changes a wrong profile or a damaged journal, so the run stops at
once with the node's reason.

| status | meaning |
| --- | --- |
| 0 | done (a coordinator: its run finished) |
| 1 | failed (`DerlError`, or a crash): a supervisor restarts a node by its restart policy |
| 2 | a usage error (`USAGE`: a flag, its value, a path given that is missing), or `InUse` |
| 78 | a node refused to start (`Refused`; 78 is EX_CONFIG of sysexits.h) |
"""

from __future__ import annotations

from typing import Final

FAILED: Final = 1
USAGE: Final = 2
IN_USE: Final = 2
REFUSED: Final = 78
FINAL: Final = frozenset({IN_USE, REFUSED})
"""Exit statuses after which a node is not restarted."""


class DerlError(Exception):
    """A reason the user reads (one line) and the exit status it ends a command with."""

    code: int = FAILED

    def __init__(self, message: str, code: int | None = None) -> None:
        super().__init__(message)
        if code is not None:
            self.code = code


class InUse(DerlError):
    """A port or a run directory another process holds."""

    code = IN_USE


class Refused(DerlError):
    """A node cannot start, and no restart would change that: its run directory holds another
    run or profile, its journal is damaged, its configuration or plan is not valid."""

    code = REFUSED
