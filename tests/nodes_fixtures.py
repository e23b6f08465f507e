"""Helpers for tests that start real derl node processes: free ports, tiny profiles,
children in their own process groups that die with the test, and what the journal says."""

from __future__ import annotations

import contextlib
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import uuid
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, TypeVar

import pytest
import yaml

from derl.messages import (
    Birth,
    Curve,
    FitnessReport,
    MessageBase,
    RunStatus,
    TrainJob,
    TrainProgress,
)
from derl.nodes.journal.segments import Journal, replay, segments
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.runtime.ports import free_port
from derl.nodes.runtime.processes import child_setup, stop_all
from derl.nodes.testing.processes import descendants
from derl.nodes.testing.waiting import wait_until
from derl.rl import PPOConfig
from derl.unimal import Genome

M = TypeVar("M", bound=MessageBase)

REPO = Path(__file__).resolve().parents[1]

TINY_PROFILE = {
    "profile": "smoke",
    "population": 2,
    "in_flight": 1,
    "tournament": 2,
    "total": 3,
    "train_steps": 4096,  # two PPO iterations of 16 envs x 128 steps: ~0.3 s per body
    "num_envs": 16,
    "lease_s": 30.0,
    "eval_top": 0,
    "eval_tasks": [],
}


class FinishedRun(NamedTuple):
    """A finished `derl run`: its run directory and what the command printed."""

    dir: Path
    printed: subprocess.CompletedProcess[str]


SMOKE_RUN = pytest.mark.xdist_group(name="smoke-run")
"""The mark of the tests that read the `smoke_run` fixture: one test process makes it for all."""


def run_id() -> str:
    return f"t{uuid.uuid4().hex[:10]}"


def write_profile(path: Path, **overrides: object) -> Path:
    path.write_text(yaml.safe_dump({**TINY_PROFILE, **overrides}))
    return path


def derl_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "derl.nodes.cli", *args]


class Processes:
    """Child processes of one test, each in its own process group (dying with the test
    process), output in `logs`/NAME.log, all stopped by `close`."""

    def __init__(self, logs: Path) -> None:
        self.logs = logs
        self.logs.mkdir(parents=True, exist_ok=True)
        self.started: dict[str, subprocess.Popen] = {}  # the latest process of each name
        self.every: list[subprocess.Popen] = []

    def start(
        self, name: str, argv: list[str], env: dict[str, str] | None = None
    ) -> subprocess.Popen:
        environment = {**os.environ, **(env or {})}
        with (self.logs / f"{name}.log").open("ab") as out:
            process = subprocess.Popen(
                argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env=environment, cwd=REPO, preexec_fn=child_setup,
            )  # fmt: skip
        self.started[name] = process
        self.every.append(process)
        return process

    def log(self, name: str) -> str:
        path = self.logs / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        process = self.started[name]
        if process.poll() is None:
            os.killpg(process.pid, sig)
        process.wait(timeout=10)

    def finish(self, process: subprocess.Popen, timeout: float = 30) -> int:
        """`process`'s exit status once it ends by itself; stopped, and a failure, after
        `timeout`."""
        try:
            return process.wait(timeout)
        except subprocess.TimeoutExpired:
            stop_all([process], timeout=2)
            raise

    def close(self) -> None:
        """SIGTERM every process group, SIGKILL what is left after 5 s."""
        stop_all(self.every, timeout=5)


@dataclass
class LocalRun:
    """A run on a loopback endpoint: its directory, profile, and its nodes' command lines."""

    dir: Path
    profile: Path
    run: str = field(default_factory=run_id)
    endpoint: str = field(default_factory=lambda: f"tcp/127.0.0.1:{free_port()}")

    @classmethod
    def at(cls, folder: Path, **profile: object) -> LocalRun:
        """A run in `folder`/run with TINY_PROFILE changed by `profile`."""
        return cls(folder / "run", write_profile(folder / "profile.yaml", **profile))

    @property
    def lease_s(self) -> float:
        return float(yaml.safe_load(self.profile.read_text())["lease_s"])

    def coordinator(self) -> list[str]:
        return derl_argv("coordinator", "--profile", str(self.profile), "--run-dir",
                         str(self.dir), "--run", self.run, "--listen", self.endpoint)  # fmt: skip

    def trainer(self, name: str) -> list[str]:
        return derl_argv("trainer", "--run", self.run, "--connect", self.endpoint, "--name", name)


class Observer:
    """The test's own view of a run on the bus: its status and training progress as heard."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.statuses: list[RunStatus] = []
        self.progress: list[TrainProgress] = []
        bus.subscribe(bus.keys.status(), self.statuses.append, (RunStatus,))
        bus.subscribe(bus.keys.all("progress"), self.progress.append, (TrainProgress,))

    def training(self, node: str, after: int = 0, timeout: float = 120) -> TrainProgress:
        """Progress of a job `node` is training now, in its first half, heard after the first
        `after` progress. A trainer publishes progress once a second and at a job's first
        iteration: the first a session hears may be a job's last but one (a session that has
        just joined misses what came before its subscription reached the trainer), and on a
        fast machine that job ends before a test can act on it."""
        return wait_until(
            lambda: next((p for p in self.progress[after:]
                          if p.node == node and 2 * p.env_steps <= p.total_steps), None),
            timeout, f"{node} in a job's first half",
        )  # fmt: skip


@contextmanager
def observe(run: LocalRun) -> Iterator[Observer]:
    """An `Observer` of `run`, a Zenoh peer connected to its endpoint, while in the block."""
    with open_session(ZenohOptions(connect=(run.endpoint,))) as session:
        yield Observer(Bus(session, run.run))


def journaled(run_dir: Path, kind: type[M]) -> list[M]:
    """The messages of type `kind` in a run's journal so far, in order."""
    if not segments(run_dir):
        return []
    return [m for m in replay(run_dir) if isinstance(m, kind)]


def births(run_dir: Path) -> list[str]:
    return [m.agent for m in journaled(run_dir, Birth)]


def jobs(run_dir: Path) -> list[TrainJob]:
    return journaled(run_dir, TrainJob)


def in_training(run_dir: Path) -> list[TrainJob]:
    """The jobs issued whose report is not journaled yet (in training, or lost)."""
    reported = {m.job for m in journaled(run_dir, FitnessReport)}
    return [j for j in jobs(run_dir) if j.job not in reported]


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


@dataclass(frozen=True)
class HandBirth:
    """A birth of a journal written by hand; a repeat takes `repeat_of`'s result (its own
    `fitness` is not used), as the coordinator makes it."""

    agent: str
    parent: str | None
    genome: Genome
    fitness: float = 0.0
    repeat_of: str | None = None


def write_hand_run(run_dir: Path, run: str, world: str, births: list[HandBirth]) -> None:
    """The journal of a finished run of `births` in birth order (the first without a parent are
    the initial population), each trained for 4,096 steps with a curve that climbs to its
    fitness, a repeat born with its earlier body's result as the coordinator does."""
    ppo = PPOConfig(total_steps=4096, num_envs=16)
    done: dict[str, Birth] = {}
    with Journal(run_dir) as journal:
        for k, b in enumerate(births):
            parent = done.get(b.parent) if b.parent else None
            generation = 0 if parent is None else parent.generation + 1
            if b.repeat_of is not None:
                first = done[b.repeat_of]
                birth = first.model_copy(update={"agent": b.agent, "parent": b.parent, "birth": k,
                                                 "generation": generation, "repeat_of": b.repeat_of,
                                                 "mutation": "gear"})  # fmt: skip
            else:
                job = TrainJob(run=run, job=f"{b.agent}.1", agent=b.agent, node="t0",
                               genome=b.genome, task=world, ppo=ppo, parent=b.parent,
                               mutation=None if parent is None else "gear", lease_s=30)  # fmt: skip
                report = FitnessReport(
                    run=run, agent=b.agent, job=job.job, node="t0", genome=b.genome,
                    fitness=b.fitness,
                    fitness_source="window", fitness_episodes=3,
                    curve=Curve(env_steps=(2048, 4096), returns=(b.fitness / 2, b.fitness)),
                    energy=50.0, cost_of_work=1.0, mass=12.0, episodes=9, env_steps=4096,
                    wall_s=1.0, steps_per_s=4096.0, checkpoint=b"",
                )  # fmt: skip
                birth = Birth(
                    run=run, agent=b.agent, parent=b.parent, job=job.job, node="t0", birth=k,
                    generation=generation, fitness=b.fitness, cost_of_work=1.0, energy=50.0,
                    mass=12.0, mutation=job.mutation, genome=b.genome,
                )  # fmt: skip
                journal.write(job)
                journal.write(report)
            journal.write(birth)
            done[b.agent] = birth


class FullDisk:
    """A disk the test fills and frees, with real write faults from the kernel (no mock of the
    journal or of the files): a small tmpfs mounted at `path` where mounting is allowed (root),
    filled with a file until writes fail with ENOSPC; else the file-size limit (RLIMIT_FSIZE) of
    the processes that write, set to the size of the journal's last segment in `path` so that
    the journal's next write fails with EFBIG (Python ignores SIGXFSZ), and so does any file
    growing past it (a checkpoint), while a process's small log file elsewhere still grows."""

    def __init__(self, path: Path, kind: str) -> None:
        self.path, self.kind = path, kind
        self.filler = path / "filler"
        self.limited: list[int] = []
        path.mkdir(parents=True, exist_ok=True)
        if kind == "tmpfs":
            subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(path)],
                           check=True, capture_output=True)  # fmt: skip

    @staticmethod
    def kinds() -> list[str]:
        """The kinds this machine allows: tmpfs where a test may mount one, and fsize."""
        if os.geteuid() != 0 or shutil.which("mount") is None:
            return ["fsize"]
        probe = Path(tempfile.mkdtemp(prefix="derl-mount-probe-"))
        try:
            mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs",
                                      str(probe)], capture_output=True).returncode == 0  # fmt: skip
            if mounted:
                subprocess.run(["umount", str(probe)], check=True)
        finally:
            probe.rmdir()
        return ["tmpfs", "fsize"] if mounted else ["fsize"]

    def fill(self, pids: list[int]) -> None:
        """Writes fail from now on (of `pids` and their children, for fsize)."""
        if self.kind == "tmpfs":
            with contextlib.suppress(OSError), self.filler.open("wb") as f:
                while True:
                    f.write(bytes(1 << 16))
                    f.flush()
            return
        journals = sorted(self.path.rglob("segment-*.mcap"))
        limit = journals[-1].stat().st_size if journals else 0
        self.limited = [p for pid in pids for p in (pid, *descendants(pid))]
        for pid in self.limited:
            resource.prlimit(pid, resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))

    def free(self) -> None:
        """Writes work again."""
        if self.kind == "tmpfs":
            self.filler.unlink(missing_ok=True)
            return
        for pid in {*self.limited, *(d for p in self.limited for d in descendants(p))}:
            with contextlib.suppress(ProcessLookupError):
                resource.prlimit(pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY,) * 2)

    def close(self) -> None:
        self.free()
        if self.kind == "tmpfs":
            subprocess.run(["umount", "-l", str(self.path)], capture_output=True)
