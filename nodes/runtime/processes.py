"""Child processes of a launcher: each in its own process group, dying with its parent."""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

PR_SET_PDEATHSIG = 1


def child_setup() -> None:
    os.setsid()
    ctypes.CDLL("libc.so.6").prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


def spawn_derl(args: list[str], log_file: Path | None = None) -> subprocess.Popen:
    """Start `derl ARGS...` with this Python; output to `log_file` (else inherited)."""
    out = open(log_file, "ab") if log_file else None  # noqa: SIM115 (the child owns it)
    try:
        return subprocess.Popen(
            [sys.executable, "-m", "derl.nodes.cli", *args],
            stdout=out,
            stderr=subprocess.STDOUT if out else None,
            stdin=subprocess.DEVNULL,
            preexec_fn=child_setup,
        )
    finally:
        if out:
            out.close()


def stop_all(processes: list[subprocess.Popen], timeout: float = 10.0) -> None:
    """SIGTERM every process group, then SIGKILL what is still there after `timeout`."""
    for process in processes:
        if process.poll() is None:
            _signal_group(process.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    for process in processes:
        try:
            process.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            _signal_group(process.pid, signal.SIGKILL)
            process.wait()


def exit_status(process: subprocess.Popen) -> int:
    """A finished process's status as a shell gives it: 128 + N when killed by signal N."""
    code = process.wait()
    return 128 - code if code < 0 else code


def _signal_group(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):  # it ended between the check and the signal
        os.killpg(pid, sig)
