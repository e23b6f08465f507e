"""`Supervisor`: starts the node processes of a launch, restarts them by their policy, stops them.

Used by `derl launch`, `derl run` and `derl study`. Restarts back off 1, 2, 4 ... 30 s. A
coordinator that exits 0 has finished the run: everything stops. A node that exits with a `FINAL`
status (it refused to start: another run's directory, a damaged journal, a port in use ...) is not
restarted, since no restart would change that; when it is the coordinator (or an ssh host's
launcher) everything stops at once and `run` raises a `DerlError` with that status and the
node's own reason (its last ``derl: ...`` line). Any other exit is a failure, restarted by its
policy (the coordinator alone: it resumes from its journal while the workers go on), except a
worker once the run is over (`over`: workers end as they hear so, before the coordinator does).
Everything stops on Ctrl-C, SIGTERM or SIGHUP (an ssh session that ends). Local processes run
with this Python (``python -m derl.nodes.cli``, the same as ``derl``); one with a launcher
(``srun ...``: a Slurm job step) runs its ``derl`` under it.
"""

from __future__ import annotations

import logging
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from derl.nodes.errors import FINAL, DerlError
from derl.nodes.launch.commands import NodeCommand
from derl.nodes.runtime.processes import child_setup, spawn_derl, stop_all

log = logging.getLogger("derl.launch")

RESTART_DELAY_S = 1.0
MAX_RESTART_DELAY_S = 30.0
REASON_PREFIX = "derl: "  # how a node's last words start (`derl.nodes.cli.main`)
STOPS_ALL = ("coordinator", "ssh")  # roles whose refusal stops the whole launch
WORKERS = ("trainer", "evaluator")  # roles that end by themselves once the run is over


@dataclass
class _Slot:
    command: NodeCommand
    process: subprocess.Popen | None = None
    restarts: int = 0
    due: float | None = None  # when a pending restart is due
    finished: bool = False
    returncode: int | None = None


class Supervisor:
    """Starts node processes, restarts them by their policy, stops them all at the end."""

    def __init__(self, commands: list[NodeCommand], log_dir: Path) -> None:
        self.slots = [_Slot(command) for command in commands]
        self.log_dir = Path(log_dir)
        self.stop = threading.Event()
        self.over = threading.Event()  # the run is over (its status said so): no worker restarts

    def _start(self, slot: _Slot) -> None:
        command = slot.command
        log_file = self.log_dir / f"{command.name}.log"
        with log_file.open("ab") as out:
            out.write(
                f"--- derl launch, start {slot.restarts}: {command.shell(slot.restarts)}\n".encode()
            )
        if command.remote is None and not command.launcher:
            slot.process = spawn_derl(command.derl_args(slot.restarts), log_file)
        else:
            slot.process = _spawn(command.argv(slot.restarts), log_file)
        slot.due = slot.returncode = None
        log.info("%s started (pid %d)%s", command.name, slot.process.pid,
                 f", restart {slot.restarts}" if slot.restarts else "")  # fmt: skip

    def run(self, poll_s: float = 0.25, tick: Callable[[], None] | None = None) -> int:
        """Start everything, supervise until the run is over or `stop` is set, calling `tick`
        after every round (to show progress); the exit code: 0 when the run finished (or every
        node ended cleanly), 1 when a node failed for good, 130 when stopped; a `DerlError`
        when the coordinator refused to start."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        code = None
        try:
            for slot in self.slots:
                if not self.stop.is_set():
                    self._start(slot)
            while code is None and not self.stop.wait(poll_s):
                code = self._step(time.monotonic())
                if tick is not None:
                    tick()
        finally:
            self.shutdown()
        return 130 if code is None else code

    def _step(self, now: float) -> int | None:
        """One supervision round; the exit code when there is nothing left to supervise."""
        for slot in self.slots:
            if slot.finished:
                continue
            if slot.due is not None:
                if self._over_for(slot.command):
                    slot.finished, slot.due = True, None
                elif now >= slot.due:
                    self._start(slot)
                continue
            if slot.process is None or slot.process.poll() is None:
                continue
            slot.returncode = code = slot.process.returncode
            command = slot.command
            if command.role == "coordinator" and code == 0:
                log.info("the coordinator finished the run: stopping this host's nodes")
                slot.finished = True
                return 0
            if code in FINAL:
                slot.finished = True
                reason = self._reason(command)
                if command.role in STOPS_ALL:
                    who = "the coordinator" if command.role == "coordinator" else command.name
                    raise DerlError(f"{who} refused: {reason}", code)
                log.error("%s refused (exit status %d, not restarted): %s", command.name, code,
                          reason)  # fmt: skip
                continue
            wanted = command.restart == "always" or (command.restart == "on-failure" and code != 0)
            wanted = wanted and not self._over_for(command)
            if wanted and slot.restarts < command.max_restarts:
                slot.restarts += 1
                delay = min(RESTART_DELAY_S * 2 ** (slot.restarts - 1), MAX_RESTART_DELAY_S)
                slot.due = now + delay
                log.warning("%s exited with %s: restart %d/%d in %.0f s", command.name, code,
                            slot.restarts, command.max_restarts, delay)  # fmt: skip
                continue
            slot.finished = True
            level = logging.INFO if code == 0 else logging.WARNING
            log.log(level, "%s exited with %s (restart: %s, %d restarts done)",
                    command.name, code, command.restart, slot.restarts)  # fmt: skip
            if command.role == "coordinator":
                log.error("the coordinator failed for good: stopping this host's nodes")
                return 1
        if all(slot.finished for slot in self.slots):
            return 0 if all(slot.returncode == 0 for slot in self.slots) else 1
        return None

    def _over_for(self, command: NodeCommand) -> bool:
        """Whether `command` is a worker of a run that is over: it is not started again."""
        return self.over.is_set() and command.role in WORKERS

    def _reason(self, command: NodeCommand) -> str:
        """What a node that ended said last (its `derl: ...` line), else where to look."""
        log_file = self.log_dir / f"{command.name}.log"
        try:
            with log_file.open("rb") as out:
                out.seek(max(0, out.seek(0, 2) - 65536))
                lines = out.read().decode(errors="replace").splitlines()
        except OSError:
            lines = []
        said = [line for line in lines if line.startswith(REASON_PREFIX)]
        return said[-1].removeprefix(REASON_PREFIX) if said else f"see {log_file}"

    def shutdown(self) -> None:
        """SIGTERM every node still running (SIGKILL after 10 s); no restarts after this."""
        stop_all([s.process for s in self.slots if s.process is not None], timeout=10)


def _spawn(argv: list[str], log_file: Path) -> subprocess.Popen:
    """Start another command (ssh, srun ...) as `spawn_derl` does: own process group, dies with
    us."""
    with log_file.open("ab") as out:
        return subprocess.Popen(
            argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            preexec_fn=child_setup,
        )  # fmt: skip
