"""The soak: a run under `derl launch` in router topology, faults drawn at random, every node
process's memory, open files and threads sampled, and the report of it all.

A real run started with `derl launch` on this host, in router topology (a `derl router`, the
coordinator, trainers and an evaluator, every node a Zenoh client of the router on loopback;
multicast off), with a small cheap profile (`PROFILE`: FT, P=8, T=4, short trainings, one
evaluation at the end). The launch's supervisor restarts a node that dies, as on a cluster. Every
`fault_every` seconds (a range) a fault drawn at random (`FAULTS`):

- SIGKILL of a trainer, the evaluator, the coordinator or the router (the supervisor starts it
  again; the coordinator resumes from its journal, the clients reconnect to the router);
- SIGSTOP of one of them for 5 to 25 s, then SIGCONT (a trainer or the evaluator stopped past
  its lease loses its job; a stopped router cuts every node off; a stopped coordinator hears
  nothing);
- garbage on every key kind of the run (`put_garbage`).

Every `SAMPLE_S` it samples each node process (the launch, the router, the coordinator and its
checkpoint writer, the trainers, the evaluator: each incarnation of each on its own) for its
resident memory, open files and threads (`/proc`). At the end, after the run finishes
(`Soak.report`):

- `finished`: `derl launch` ended with status 0 (the coordinator finished the run and wrote its
  results);
- `born_once`: every child of the run is born exactly once, or given up;
- `flat`: for every incarnation that lived long enough (past its warm-up, `WARMUP`, by at least
  a quarter of the soak), the median of each figure over its last fifth of samples is within 10%
  of the median over the fifth after its warm-up.

The faults go on until the run ends, or for at most twice `minutes` (then the run is left to
finish). bench/soak.py runs it for half an hour; tests/test_soak.py for a minute.
"""

from __future__ import annotations

import contextlib
import os
import random
import signal
import statistics
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import yaml
import zenoh

from derl.messages import Birth, ChildFailed
from derl.nodes.journal.segments import replay
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.runtime.ports import free_port
from derl.nodes.runtime.processes import child_setup, stop_all
from derl.nodes.testing.faults import put_garbage
from derl.nodes.testing.processes import descendants, sample

TRAIN_STEPS = 16384  # a training's steps, unless told
PROFILE = {
    "profile": "smoke",
    "population": 8,
    "tournament": 4,
    "train_steps": TRAIN_STEPS,
    "num_envs": 16,
    "lease_s": 15.0,
    "eval_top": 1,
    "eval_tasks": ["patrol"],
    "eval_steps": 4096,
}
SAMPLE_S = 2.0
WARMUP = (60.0, 0.2)  # an incarnation's warm-up: this many s, or this share of the soak if less
FLAT = 1.10  # the largest ratio of late to early medians that counts as flat
STOP_S = (5.0, 25.0)
FAULTS = (
    "SIGKILL trainer",
    "SIGSTOP trainer",
    "SIGKILL evaluator",
    "SIGSTOP evaluator",
    "SIGKILL coordinator",
    "SIGSTOP coordinator",
    "SIGKILL router",
    "SIGSTOP router",
    "garbage",
)
ROLES = ("router", "coordinator", "trainer", "evaluator")


# --- the processes ---------------------------------------------------------------------------


def label(pid: int) -> str | None:
    """What process `pid` is: `derl launch`, a node's role (and a worker's name), the checkpoint
    writer, or None for another process."""
    try:
        argv = (Path(f"/proc/{pid}") / "cmdline").read_bytes().decode().split("\0")
    except OSError:
        return None
    if any(arg.endswith("checkpoint_writer.py") for arg in argv):
        return "checkpoint_writer"
    if "derl.nodes.cli" not in argv[:-1]:
        return None
    command = argv[argv.index("derl.nodes.cli") + 1]
    if command in ("trainer", "evaluator") and "--name" in argv:
        return f"{command} {argv[argv.index('--name') + 1]}"
    return command if command in (*ROLES, "launch") else None


def node_processes(root: int) -> dict[int, str]:
    """The node processes under `root` (the launch), by pid, with their labels."""
    labels = {pid: label(pid) for pid in (root, *descendants(root))}
    return {pid: name for pid, name in labels.items() if name is not None}


@dataclass
class Incarnation:
    """One process of a node, from its first sample to its last."""

    label: str
    pid: int
    samples: list[tuple[float, dict[str, float]]] = field(default_factory=list)

    def judged(self, warmup_s: float, span_s: float) -> dict[str, object] | None:
        """Early and late medians of each figure and their ratios, if this incarnation lived
        `span_s` past its warm-up; else None."""
        if not self.samples:
            return None
        start = self.samples[0][0]
        after = [(t, s) for t, s in self.samples if t >= start + warmup_s]
        if len(after) < 10 or after[-1][0] - after[0][0] < span_s:
            return None
        fifth = max(2, len(after) // 5)
        out: dict[str, object] = {"lived_s": round(after[-1][0] - start)}
        flat = True
        for figure in ("rss_mb", "open_files", "threads"):
            early = statistics.median(s[figure] for _, s in after[:fifth])
            late = statistics.median(s[figure] for _, s in after[-fifth:])
            ratio = late / early if early else 1.0
            flat = flat and ratio <= FLAT
            out[figure] = {"early": round(early, 1), "late": round(late, 1),
                           "ratio": round(ratio, 3)}  # fmt: skip
        out["flat"] = flat
        return out


# --- the soak --------------------------------------------------------------------------------


@dataclass
class Soak:
    work: Path
    minutes: float
    fault_every: tuple[float, float]
    total: int
    trainers: int = 2
    seed: int = 0
    train_steps: int = TRAIN_STEPS
    run: str = "soak"
    faults: list[dict[str, object]] = field(default_factory=list)
    incarnations: dict[int, Incarnation] = field(default_factory=dict)
    stopped: dict[int, float] = field(default_factory=dict)  # pid -> when to SIGCONT it

    @property
    def run_dir(self) -> Path:
        return self.work / "run"

    def launch_file(self, port: int) -> Path:
        profile = self.work / "profile.yaml"
        profile.write_text(yaml.safe_dump({**PROFILE, "total": self.total,
                                           "train_steps": self.train_steps}))  # fmt: skip
        endpoint = f"tcp/127.0.0.1:{port}"
        nodes = [
            {"role": "router", "restart": "always", "max_restarts": 10_000},
            {"role": "coordinator", "restart": "on-failure", "max_restarts": 10_000},
            {"role": "trainer", "count": self.trainers, "restart": "on-failure",
             "max_restarts": 10_000},
            {"role": "evaluator", "restart": "on-failure", "max_restarts": 10_000},
        ]  # fmt: skip
        data = {
            "run": self.run,
            "run_dir": str(self.run_dir),
            "profile": str(profile),
            "seed": self.seed,
            "topology": {"kind": "router", "endpoint": endpoint, "host": "local"},
            "hosts": [{"name": "local", "address": "localhost", "nodes": nodes}],
        }
        path = self.work / "launch.yaml"
        path.write_text(yaml.safe_dump(data))
        return path

    def execute(self) -> dict[str, object]:
        port = free_port()
        launch_file = self.launch_file(port)
        log = (self.work / "launch.log").open("ab")
        started = time.monotonic()
        launch = subprocess.Popen(
            [sys.executable, "-m", "derl.nodes.cli", "launch", str(launch_file)],
            stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            preexec_fn=child_setup,
        )  # fmt: skip
        rng = random.Random(self.seed)
        options = ZenohOptions(mode="client", connect=(f"tcp/127.0.0.1:{port}",))
        stray: list[zenoh.LivelinessToken] = []
        try:
            time.sleep(3.0)  # the router listens
            with open_session(options) as session:
                bus = Bus(session, self.run)
                next_fault = time.monotonic() + rng.uniform(*self.fault_every)
                next_sample = 0.0
                while launch.poll() is None:
                    now = time.monotonic()
                    self._resume_due(now)
                    if now >= next_sample:
                        self._sample(launch.pid, now - started)
                        next_sample = now + SAMPLE_S
                    # faults for the minutes asked (twice that at most), then the run may finish:
                    # under load an evaluation can outlast a fault every few seconds for ever
                    if now >= next_fault and now - started < 2 * 60 * self.minutes:
                        self._fault(rng, launch.pid, bus, stray, now - started)
                        next_fault = now + rng.uniform(*self.fault_every)
                    time.sleep(0.2)
                self._resume_due(float("inf"))
        finally:
            self._resume_due(float("inf"))
            stop_all([launch], timeout=10)
            log.close()
        return self.report(launch.returncode, time.monotonic() - started)

    def _sample(self, root: int, at: float) -> None:
        for pid, name in node_processes(root).items():
            figures = sample(pid)
            if figures is not None:
                self.incarnations.setdefault(pid, Incarnation(name, pid)).samples.append(
                    (at, figures)
                )

    def _resume_due(self, now: float) -> None:
        for pid, due in list(self.stopped.items()):
            if due <= now:
                del self.stopped[pid]
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGCONT)

    def _fault(self, rng: random.Random, root: int, bus: Bus, stray: list, at: float) -> None:
        kind = rng.choice(FAULTS)
        fault: dict[str, object] = {"at_s": round(at, 1), "kind": kind}
        if kind == "garbage":
            put, token = put_garbage(bus)
            stray.append(token)
            fault["payloads"] = put
        else:
            how, role = kind.split()
            targets = [pid for pid, name in node_processes(root).items()
                       if name.split()[0] == role and pid not in self.stopped]  # fmt: skip
            if not targets:
                fault["skipped"] = f"no {role} running"
                self.faults.append(fault)
                return
            pid = rng.choice(targets)
            fault["target"] = self.incarnations.get(pid, Incarnation(role, pid)).label
            try:
                if how == "SIGKILL":
                    os.kill(pid, signal.SIGKILL)
                else:
                    os.kill(pid, signal.SIGSTOP)
                    stopped_s = rng.uniform(*STOP_S)
                    self.stopped[pid] = time.monotonic() + stopped_s
                    fault["stopped_s"] = round(stopped_s, 1)
            except ProcessLookupError:
                fault["skipped"] = "it had just ended"
        self.faults.append(fault)

    def report(self, code: int | None, wall_s: float) -> dict[str, object]:
        births = [m for m in replay(self.run_dir) if isinstance(m, Birth | ChildFailed)]
        born = Counter(m.agent for m in births if isinstance(m, Birth))
        given_up = {m.agent for m in births if isinstance(m, ChildFailed)}
        warmup_s = min(WARMUP[0], WARMUP[1] * wall_s)
        span_s = wall_s / 4
        processes: dict[str, list[dict[str, object]]] = {}
        for incarnation in self.incarnations.values():
            judged = incarnation.judged(warmup_s, span_s)
            if judged is not None:
                processes.setdefault(incarnation.label, []).append(judged)
        started = Counter(i.label for i in self.incarnations.values())
        kinds = Counter(str(f["kind"]) for f in self.faults if "skipped" not in f)
        return {
            "minutes_asked": self.minutes,
            "wall_s": round(wall_s),
            "lasted_long_enough": wall_s >= 60 * self.minutes,
            "finished": code == 0 and (self.run_dir / "summary.json").exists(),
            "launch_exit_code": code,
            "total": self.total,
            "born": sum(born.values()),
            "given_up": len(given_up),
            "born_twice": sorted(c for c, n in born.items() if n > 1),
            "born_once": max(born.values(), default=1) == 1
            and len(born) + len(given_up) == self.total,
            "faults": len(self.faults) - sum("skipped" in f for f in self.faults),
            "faults_by_kind": dict(sorted(kinds.items())),
            "fault_log": self.faults,
            "incarnations": dict(sorted(started.items())),
            "warmup_s": round(warmup_s),
            "judged_processes": processes,
            "flat": all(j["flat"] for judged in processes.values() for j in judged),
        }
