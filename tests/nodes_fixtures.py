"""Helpers for tests that start real derl node processes: free ports, tiny profiles, waiting,
children in their own process groups that die with the test, and what the journal says."""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import yaml

from messages import Birth, TrainJob
from nodes.journal.segments import replay, segments
from nodes.runtime.processes import stop_all

REPO = Path(__file__).resolve().parents[1]

TINY_PROFILE = {
    "profile": "smoke",
    "population": 2,
    "tournament": 2,
    "total": 3,
    "train_steps": 4096,  # two PPO iterations of 16 envs x 128 steps: a few seconds per body
    "num_envs": 16,
    "lease_s": 30.0,
    "eval_top": 0,
    "eval_tasks": [],
}


def run_id() -> str:
    return f"t{uuid.uuid4().hex[:10]}"


def free_port(host: str = "127.0.0.1", span: int = 1) -> int:
    """A port P such that P .. P + span - 1 can be bound on `host` now (a small race remains)."""
    for _ in range(200):
        with socket.socket() as probe:
            probe.bind((host, 0))
            port = probe.getsockname()[1]
        if port + span > 65535:
            continue
        try:
            for k in range(1, span):
                with socket.socket() as other:
                    other.bind((host, port + k))
        except OSError:
            continue
        return port
    raise RuntimeError(f"no {span} free consecutive ports on {host}")


def write_profile(path: Path, **overrides: object) -> Path:
    path.write_text(yaml.safe_dump({**TINY_PROFILE, **overrides}))
    return path


def wait_for(condition: Callable[[], object], timeout: float, what: str) -> object:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _child_setup() -> None:  # own process group, and die with the test process
    os.setsid()
    ctypes.CDLL("libc.so.6").prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def derl_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "nodes.cli", *args]


class Processes:
    """Child processes of one test, each in its own process group, all killed by `close`."""

    def __init__(self, logs: Path) -> None:
        self.logs = logs
        self.logs.mkdir(parents=True, exist_ok=True)
        self.started: dict[str, subprocess.Popen] = {}

    def start(
        self, name: str, argv: list[str], env: dict[str, str] | None = None
    ) -> subprocess.Popen:
        environment = {**os.environ, "PYTHONPATH": str(REPO), **(env or {})}
        with (self.logs / f"{name}.log").open("ab") as out:
            process = subprocess.Popen(
                argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env=environment, cwd=REPO, preexec_fn=_child_setup,
            )  # fmt: skip
        self.started[name] = process
        return process

    def log(self, name: str) -> str:
        path = self.logs / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        process = self.started[name]
        if process.poll() is None:
            os.killpg(process.pid, sig)
        process.wait(timeout=10)

    def close(self) -> None:
        """SIGTERM every process group, SIGKILL what is left after 5 s."""
        stop_all(list(self.started.values()), timeout=5)


def births(run_dir: Path) -> list[str]:
    if not segments(run_dir):
        return []
    return [m.child for m in replay(run_dir) if isinstance(m, Birth)]


def jobs(run_dir: Path) -> list[TrainJob]:
    if not segments(run_dir):
        return []
    return [m for m in replay(run_dir) if isinstance(m, TrainJob)]


def assert_born_once(run_dir: Path, total: int) -> None:
    born = births(run_dir)
    assert len(born) == total, born
    assert max(Counter(born).values()) == 1, born


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by its parent) is not alive
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False
