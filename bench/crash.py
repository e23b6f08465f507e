"""Crash consistency of a run directory, checked at every point of a real run's writes; prints JSON.

1. Record. A small real run (the smoke profile: P=4, T=2, 10 bodies, no evaluation) of a real
   `derl coordinator` process and two simulated trainers (`Trainer`: each answers its job at once
   with its body, a fitness and checkpoint bytes that depend only on the child, and sends the
   report again every 0.5 s until it is acknowledged or rejected, as `derl trainer` does) over real
   Zenoh, under `strace -f`: every open, write (with its bytes), truncate, rename, link, unlink,
   mkdir, fsync, fdatasync and syncfs of the coordinator and its checkpoint writer process, and
   every mark of a trainer (a job received, an Ack, a Reject, written to a file of marks), in the
   order they completed (a trainer marks a message after receiving it, so after every operation
   the coordinator did before publishing it).
2. Model (`Disk`). The run directory after each operation, twice: as a process kill leaves it
   (every operation done: the page cache survives) and as a power cut does under POSIX's rules,
   nothing more: a file's data is on the disk once an fsync or fdatasync of it, or a syncfs of its
   file system, is over; a directory entry (a file or folder created, renamed, linked, unlinked)
   once an fsync of its directory, or a syncfs, is over; a file created whose data never reached the
   disk is empty. Torn writes: each write into a journal segment is also cut inside (at each of its
   records' boundaries and 1, 9, half and all-but-1 bytes into each record), over the kill state and
   over the power state with the segment's writes since its last fsync there (a crash persists
   appends in order: ext4's default), and with the rest of the write zeros (a file grown whose new
   data never reached the disk: XFS, ext4 data=writeback). Not modelled: unsynced writes persisted
   out of order across files or pages beyond that (states between a power state and its kill
   state).
3. Check. Each state, built in a folder, first as the coordinator's start does it (the segment it
   resumes from cut back to its last whole record: `cut_torn_tail`); states equal then (and equal in
   what the trainers knew) are checked once. A state is checked by a coordinator started on it that
   runs the run to its end with the same two trainers, each as it was at the cut: one that held a
   job and had not heard its Ack sends its report again, the others ask for work (`derl trainer`
   after a coordinator restart). Invariants: the coordinator starts (a crash never leaves what it
   refuses); every job a trainer had received is in the journal; every birth whose Ack a trainer
   had received is in the journal, from that job, with its checkpoint file holding that trainer's
   bytes, at the start and at the end; no child is born twice; the run finishes with every body
   born, every checkpoint file in place, summary.json and the best bodies' folders with their
   checkpoints. `check` drives the coordinator's own code in this process (`Coordinator` built on
   the folder: the replay and everything a start does; then its handlers, group commit and outbox
   as the serve loop calls them, and the loop's end: five rounds of 'done', the results written at
   the last; without a bus: what it would publish goes to the trainers); `--real K` also checks K
   states, drawn at random, with a real `derl coordinator` process and the trainers over real
   Zenoh.

Prints: operations recorded, cut points, states tried by kind, distinct states, states checked in
this process and with real processes, failures (each: the cut, the kind of state, what broke),
time. Run: python bench/crash.py [--real K] [--sample N (check N distinct states drawn at random,
not all)] [--work DIR] (about 8 minutes on a shared 2-core machine for every state).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

from derl.evolution import EvolutionConfig, load_profile  # noqa: E402
from derl.messages import (  # noqa: E402
    Ack,
    Birth,
    Cancel,
    FitnessReport,
    MessageBase,
    Reject,
    RunStatus,
    TrainJob,
    WorkerReady,
    decode,
    encode,
)
from derl.nodes.journal.reader import JournalDamaged  # noqa: E402
from derl.nodes.journal.segments import cut_torn_tail, replay, segments  # noqa: E402
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session  # noqa: E402
from derl.policy_check import untrained_policy  # noqa: E402
from derl.unimal import Genome  # noqa: E402

RUN = "crash"
PROFILE = {"profile": "smoke", "total": 10, "eval_top": 0, "eval_tasks": [], "lease_s": 60.0}
NODES = ("t1", "t2")
RESEND_S = 0.5
SYSCALLS = ("openat,creat,write,pwrite64,writev,pwritev,pwritev2,lseek,ftruncate,truncate,"
            "rename,renameat,renameat2,link,linkat,unlink,unlinkat,mkdir,mkdirat,fsync,"
            "fdatasync,syncfs,sync,close")  # fmt: skip


def config() -> EvolutionConfig:
    """The run's profile, as `derl coordinator --profile crash.yaml` reads it."""
    fields = {k: v for k, v in PROFILE.items() if k != "profile"}
    base = load_profile(str(PROFILE["profile"])).model_dump()
    return EvolutionConfig.model_validate({**base, **fields, "name": "crash"})


# --- 1. the simulated trainers ---------------------------------------------------------------


@cache
def checkpoint_of(child: str, genome: Genome, world: str) -> bytes:
    """The policy a trainer reports for `child` of body `genome` (an untrained one, its weights
    drawn from the child's name: each child's own; tens of kB, so a write spans pages); made
    once (its orthogonal weights cost tens of ms, and every state's check compares them)."""
    seed = int.from_bytes(hashlib.sha256(child.encode()).digest()[:4], "little")
    return untrained_policy(genome, world, seed)


@cache
def _report(job: TrainJob) -> FitnessReport:
    """`job`'s report (bench/bus.py's fake result, with the job's body) with this child's
    checkpoint and fitness: later children are fitter (as evolution hopes), so
    the last ones born are the best, whose checkpoints the run's results must hold."""
    from bus import _report as report_of

    fitness = int(job.child[1:]) + (50.0 if job.child.startswith("c") else 0.0)
    report = report_of(job.run, job, fitness)
    checkpoint = checkpoint_of(job.child, job.genome, job.task)
    return report.model_copy(update={"env_steps": job.steps, "checkpoint": checkpoint})


@dataclass
class Trainer:
    """What a simulated trainer does with what it hears, whatever carries its messages: a job is
    answered at once, and the report sent again (`pending`) until acknowledged or rejected."""

    node: str
    job: TrainJob | None = None
    acknowledged: bool = True  # its job's report is answered (or it has none)
    marks: list[str] = field(default_factory=list)

    def hear(self, msg: MessageBase) -> list[MessageBase]:
        """What it sends in answer to `msg` (a job, an Ack or Reject, a Cancel of its node)."""
        if isinstance(msg, TrainJob):
            if self.job is not None and msg.job == self.job.job and not self.acknowledged:
                return []  # the order sent again while it answers: its report goes on
            self.job, self.acknowledged = msg, False
            self.marks.append(f"job {self.node} {msg.job} {msg.child}")
            return [_report(msg)]
        if isinstance(msg, Ack | Reject) and self.job is not None and msg.job == self.job.job:
            if not self.acknowledged:
                kind = "ack" if isinstance(msg, Ack) else "reject"
                self.marks.append(f"{kind} {self.node} {msg.job} {msg.child}")
            self.acknowledged = True
            return [self.ready()]
        if isinstance(msg, Cancel) and self.job is not None and msg.job == self.job.job:
            self.acknowledged = True
            return [self.ready()]
        return []

    def pending(self) -> FitnessReport | None:
        return None if self.acknowledged or self.job is None else _report(self.job)

    def ready(self) -> WorkerReady:
        return WorkerReady(run=RUN, node=self.node, role="trainer", host="sim", pid=1)

    def again(self) -> MessageBase:
        """What it sends while it waits: its report again, or another ask for work."""
        pending = self.pending()
        return self.ready() if pending is None else pending


def zenoh_trainers(endpoint: str, trainers: list[Trainer], marks: Path | None,
                   timeout: float = 300.0) -> None:  # fmt: skip
    """Run `trainers` on one Zenoh session until the run is done (each mark appended to `marks`
    by a write of its own, so `strace` orders it among the coordinator's operations)."""
    lock = threading.Lock()
    done = threading.Event()
    out = os.open(marks, os.O_WRONLY | os.O_CREAT | os.O_APPEND) if marks else None
    with open_session(ZenohOptions(connect=(endpoint,))) as session:
        bus = Bus(session, RUN)
        tokens = [bus.token("trainer", t.node) for t in trainers]

        def hearing(trainer: Trainer) -> Callable[[MessageBase], None]:
            def on(msg: MessageBase) -> None:
                with lock:
                    before = len(trainer.marks)
                    answers = trainer.hear(msg)
                    for mark in trainer.marks[before:]:
                        if out is not None:
                            os.write(out, f"{mark}\n".encode())
                for answer in answers:
                    bus.publish(answer)

            return on

        for trainer in trainers:
            bus.subscribe(bus.keys.job(trainer.node), hearing(trainer), (TrainJob, Cancel))
            bus.subscribe(bus.keys.ack(trainer.node), hearing(trainer), (Ack, Reject))
        bus.subscribe(bus.keys.status(), lambda s: s.done and done.set(), (RunStatus,))
        deadline = time.monotonic() + timeout
        while True:  # until the run is done and no report waits for its answer
            if done.wait(RESEND_S):
                time.sleep(RESEND_S)
            if time.monotonic() > deadline:
                raise TimeoutError("the run did not finish")
            with lock:
                waiting = [t.again() for t in trainers if not done.is_set() or t.pending()]
            if not waiting:
                break
            for msg in waiting:
                bus.publish(msg)
        for token in tokens:
            token.undeclare()
    if out is not None:
        os.close(out)


def _record_run(work: Path) -> None:
    """The recorded run (this process and its coordinator run under strace)."""
    from derl.nodes.runtime.processes import spawn_derl, stop_all

    profile = work / "crash.yaml"
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    coordinator = spawn_derl(
        ["coordinator", "--run", RUN, "--profile", str(profile), "--run-dir", str(work / "run"),
         "--listen", endpoint], work / "coordinator.log",
    )  # fmt: skip
    try:
        zenoh_trainers(endpoint, [Trainer(node) for node in NODES], work / "marks")
        if coordinator.wait(60) != 0:
            raise RuntimeError(f"the coordinator failed: {(work / 'coordinator.log').read_text()}")
    finally:
        stop_all([coordinator])


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def record(work: Path) -> Path:
    """Run the small run under strace in `work`; the trace's path."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "crash.yaml").write_text(yaml.safe_dump(PROFILE))
    trace = work / "trace"
    done = subprocess.run(
        ["strace", "-f", "-qq", "-y", "-xx", "-s", "100000000", "--seccomp-bpf", "-e",
         f"trace={SYSCALLS}",
         "-o", str(trace), sys.executable, __file__, "--record-in", str(work)],
        capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"the recorded run failed:\n{done.stdout}\n{done.stderr}")
    return trace


# --- 2. the trace and the model of the disk --------------------------------------------------


@dataclass(frozen=True)
class Op:
    """One operation of the trace, in run-directory terms (paths relative to it)."""

    kind: str  # create, write, truncate, rename, link, unlink, mkdir, fsync, syncfs, mark
    path: str = ""
    other: str = ""  # rename/link: the new name
    offset: int = 0  # write: where
    size: int = 0  # truncate: the length
    data: bytes = b""  # write: the bytes written
    mark: str = ""


_LINE = re.compile(r"^(\d+) +(.*)$")
_FD = r"(\d+)<([^>]*)>"
_STR = r'"((?:[^"\\]|\\.)*)"'
_DIRFD = r"(?:AT_FDCWD|\d+)(?:<[^>]*>)?"
_TWO = rf"(?:{_DIRFD}, )?{_STR}, (?:{_DIRFD}, )?{_STR}"  # two paths (and their folders)
_PATTERNS = {
    "openat": re.compile(rf"^openat\({_DIRFD}, {_STR}, ([A-Z_|0-9]+)(?:, \d+)?\) = (\d+)<([^>]*)>"),
    "write": re.compile(rf"^write\({_FD}, .*\) = (\d+)$"),
    "writev": re.compile(rf"^writev\({_FD}, .*\) = (\d+)$"),
    "pwrite64": re.compile(rf"^pwrite64\({_FD}, .*, \d+, (\d+)\) = (\d+)$"),
    "lseek": re.compile(rf"^lseek\({_FD}, -?\d+, SEEK_\w+\) = (\d+)$"),
    "ftruncate": re.compile(rf"^ftruncate\({_FD}, (\d+)\) = 0$"),
    "rename": re.compile(rf"^rename(?:at2?)?\({_TWO}(?:, \w+)?\) = 0$"),
    "link": re.compile(rf"^link(?:at)?\({_TWO}(?:, \w+)?\) = 0$"),
    "unlink": re.compile(rf"^unlink(?:at)?\((?:{_DIRFD}, )?{_STR}(?:, \w+)?\) = 0$"),
    "mkdir": re.compile(rf"^mkdir(?:at)?\((?:{_DIRFD}, )?{_STR}, \d+\) = 0$"),
    "fsync": re.compile(rf"^(?:fsync|fdatasync)\({_FD}\) = 0$"),
    "syncfs": re.compile(rf"^syncfs\({_FD}\) = 0$"),
    "close": re.compile(rf"^close\({_FD}\) = 0$"),
}


def parse_trace(trace: Path, run_dir: Path, marks: Path) -> list[Op]:
    """The operations on `run_dir` and the marks written to `marks`, in the order strace saw
    them complete (a call another one interrupted counts when it resumed)."""
    root, mark_file = str(run_dir), str(marks)
    pending: dict[str, str] = {}
    positions: dict[tuple[str, str], int] = {}  # (fd, path) -> offset
    ops: list[Op] = []

    def inside(printed: str) -> str | None:
        path = _bytes(printed).decode()
        if path == root:
            return "."
        return path[len(root) + 1 :] if path.startswith(root + "/") else None

    for raw in trace.read_text(errors="replace").splitlines():
        line = _LINE.match(raw)
        if line is None:
            continue
        pid, call = line.groups()
        if call.endswith("<unfinished ...>"):
            pending[pid] = call[: -len("<unfinished ...>")].rstrip()
            continue
        if call.startswith("<... "):
            call = pending.pop(pid, "") + call.split("resumed>", 1)[1]
        call = re.sub(r"\)\s+= ", ") = ", call)  # strace aligns a resumed call's result
        name = call.split("(", 1)[0]
        kind = {"renameat": "rename", "renameat2": "rename", "linkat": "link", "unlinkat":
                "unlink", "mkdirat": "mkdir", "fdatasync": "fsync"}.get(name, name)  # fmt: skip
        pattern = _PATTERNS.get(kind)
        match = pattern.match(call) if pattern else None
        if match is None:
            continue
        if kind == "openat":
            _, flags, fd, path = match.groups()
            positions[(fd, path)] = 0
            if (at := inside(path)) is not None and "O_CREAT" in flags:
                ops.append(Op("create", at))
            if at is not None and "O_TRUNC" in flags:
                ops.append(Op("truncate", at, size=0))
        elif kind in ("write", "writev", "pwrite64"):
            fd, path, *rest = match.groups()
            written = int(rest[-1])
            data = b"".join(_bytes(text) for text in re.findall(_STR, call))[:written]
            if _bytes(path).decode() == mark_file:
                ops.append(Op("mark", mark=data.decode().strip()))
            offset = int(rest[0]) if kind == "pwrite64" else positions.get((fd, path), 0)
            if kind != "pwrite64":
                positions[(fd, path)] = offset + written
            if (at := inside(path)) is not None and written:
                ops.append(Op("write", at, offset=offset, data=data))
        elif kind == "lseek":
            fd, path, offset = match.groups()
            positions[(fd, path)] = int(offset)
        elif kind == "ftruncate":
            fd, path, size = match.groups()
            if (at := inside(path)) is not None:
                ops.append(Op("truncate", at, size=int(size)))
        elif kind in ("rename", "link"):
            old, new = inside(match[1]), inside(match[2])
            if old is not None and new is not None:
                ops.append(Op(kind, old, new))
        elif kind in ("unlink", "mkdir"):
            if (at := inside(match[1])) is not None:
                ops.append(Op(kind, at))
        elif kind in ("fsync", "syncfs"):
            if (at := inside(match[2])) is not None:
                ops.append(Op(kind, at))
        elif kind == "close":
            positions.pop(match.groups(), None)
    return ops


def _bytes(text: str) -> bytes:
    """The bytes of a string or path strace printed with -xx (every byte as \\xNN)."""
    return bytes.fromhex(text.replace("\\x", ""))


DIR = None  # a folder, in a state's content


@dataclass
class Disk:
    """The run directory's files after each operation: what is done (`names`, `data`: the page
    cache) and what is on the disk (`durable_names`, `durable_data`); names map to inodes."""

    names: dict[str, int | None] = field(default_factory=lambda: {".": None})
    data: dict[int, bytearray] = field(default_factory=dict)
    durable_names: dict[str, int | None] = field(default_factory=lambda: {".": None})
    durable_data: dict[int, bytes] = field(default_factory=dict)
    inodes: int = 0

    def apply(self, op: Op) -> None:
        names = self.names
        if op.kind == "mkdir":
            names[op.path] = DIR
        elif op.kind == "create":
            if op.path not in names:
                self.inodes += 1
                names[op.path] = self.inodes
                self.data[self.inodes] = bytearray()
        elif op.kind == "truncate":
            content = self.data[names[op.path]]
            del content[op.size :]
            content.extend(bytes(op.size - len(content)))
        elif op.kind == "write":
            inode = names[op.path]
            content = self.data[inode]
            if len(content) < op.offset:
                content.extend(bytes(op.offset - len(content)))
            content[op.offset : op.offset + len(op.data)] = op.data
        elif op.kind == "rename":
            names[op.other] = names.pop(op.path)
        elif op.kind == "link":
            names[op.other] = names[op.path]
        elif op.kind == "unlink":
            del names[op.path]
        elif op.kind == "fsync":
            inode = names[op.path]
            if inode is DIR:  # the folder's entries are on the disk
                for name in [n for n in self.durable_names if _parent(n) == op.path]:
                    del self.durable_names[name]
                self.durable_names |= {n: i for n, i in names.items() if _parent(n) == op.path}
            else:
                self.durable_data[inode] = bytes(self.data[inode])
        elif op.kind == "syncfs":
            self.durable_names = dict(names)
            self.durable_data = {i: bytes(d) for i, d in self.data.items()}

    def killed(self) -> dict[str, bytes | None]:
        """What a process kill leaves: every operation done."""
        return {n: None if i is DIR else bytes(self.data[i]) for n, i in self.names.items()}

    def powered_off(self) -> dict[str, bytes | None]:
        """What a power cut leaves: what is on the disk (a name whose folder's entry is not,
        is not either; a file whose data never reached the disk is empty)."""
        state: dict[str, bytes | None] = {}
        for name in sorted(self.durable_names, key=lambda n: n.count("/")):
            if name != "." and _parent(name) not in state:
                continue
            inode = self.durable_names[name]
            state[name] = None if inode is DIR else self.durable_data.get(inode, b"")
        return state


def _files(folder: Path) -> dict[str, bytes | None]:
    """A folder's content, as a state holds it."""
    files: dict[str, bytes | None] = {".": DIR}
    for path in folder.rglob("*"):
        files[str(path.relative_to(folder))] = DIR if path.is_dir() else path.read_bytes()
    return files


def _parent(name: str) -> str:
    return name.rsplit("/", 1)[0] if "/" in name else "."


def _torn(write: bytes) -> list[int]:
    """Where to cut a journal write inside: each record boundary, and 1, 9, half and all but 1
    bytes into each record."""
    cuts, at = set(), 0
    while at + 9 <= len(write):
        end = min(len(write), at + 9 + int.from_bytes(write[at + 1 : at + 9], "little"))
        cuts |= {at, at + 1, at + 9, (at + end) // 2, end - 1}
        at = end
    return sorted(c for c in cuts if 0 < c < len(write))


@dataclass(frozen=True)
class Knowledge:
    """What the trainers knew at a cut: each one's job and whether its report was answered,
    the jobs received, the acknowledged births (child -> job)."""

    holding: tuple[tuple[str, str | None, bool], ...]  # (node, job, answered)
    received: frozenset[str]
    acked: tuple[tuple[str, str], ...]


@dataclass
class Cut:
    index: int  # operations done
    kind: str  # kill, power, kill-torn, power-torn, power-zeros
    state: dict[str, bytes | None]
    knowledge: Knowledge
    torn_at: int = 0


def cuts(ops: list[Op], run_dir: Path) -> Iterator[Cut]:
    """Every crash state of the recorded run (see the module's docstring)."""
    disk = Disk()
    holding: dict[str, tuple[str | None, bool]] = {node: (None, True) for node in NODES}
    received: set[str] = set()
    acked: dict[str, str] = {}

    def knowledge() -> Knowledge:
        held = tuple((n, j, a) for n, (j, a) in sorted(holding.items()))
        return Knowledge(held, frozenset(received), tuple(sorted(acked.items())))

    for index in range(len(ops) + 1):
        known = knowledge()
        yield Cut(index, "kill", disk.killed(), known)
        yield Cut(index, "power", disk.powered_off(), known)
        if index == len(ops):
            if disk.killed() != _files(run_dir):  # the model went wrong somewhere
                raise RuntimeError("the trace's operations do not give the run's files")
            break
        op = ops[index]
        if op.kind == "write" and op.path.startswith("journal/"):
            written = op.data
            done = bytes(disk.data[disk.names[op.path]][: op.offset])  # the writes before it
            for at in _torn(written):
                killed = disk.killed()
                killed[op.path] = done + written[:at]
                yield Cut(index, "kill-torn", killed, known, at)
                powered = disk.powered_off()
                if op.path in powered:
                    powered[op.path] = done + written[:at]
                    yield Cut(index, "power-torn", powered, known, at)
                    zeros = dict(powered)
                    zeros[op.path] = done + written[:at] + bytes(len(written) - at)
                    yield Cut(index, "power-zeros", zeros, known, at)
        if op.kind == "mark":
            what, node, job, *child = op.mark.split()
            if what == "job":
                holding[node] = (job, False)
                received.add(job)
            elif what in ("ack", "reject"):
                holding[node] = (job, True)
                if what == "ack":
                    acked[child[0]] = job
        disk.apply(op)


# --- 3. checking a state -----------------------------------------------------------------------


def build(state: dict[str, bytes | None], folder: Path) -> None:
    folder.mkdir(parents=True)
    for name, content in sorted(state.items(), key=lambda item: item[0].count("/")):
        if name == ".":
            continue
        path = folder / name
        if content is DIR:
            path.mkdir()
        else:
            path.write_bytes(content)


_SEGMENT = re.compile(r"journal/segment-\d+\.mcap")


def normalized(state: dict[str, bytes | None], scratch: Path) -> str:
    """A digest of `state` as a coordinator's start makes it first: the segment it resumes from
    cut back to its last whole record (`cut_torn_tail`; JournalDamaged if that is damage)."""
    state = dict(state)
    found = sorted(name for name in state if _SEGMENT.fullmatch(name))
    if found:
        scratch.write_bytes(state[found[-1]] or b"")
        cut_torn_tail(scratch)
        state[found[-1]] = scratch.read_bytes()
    digest = hashlib.sha256()
    for name, content in sorted(state.items()):
        digest.update(name.encode() + b"\0" + (b"/" if content is DIR else b"f" + content))
    return digest.hexdigest()


class Heard:
    """In place of the bus when the coordinator's handlers are driven in this process: what it
    publishes, in order."""

    def __init__(self) -> None:
        self.messages: list[MessageBase] = []

    def publish(self, msg: MessageBase, data: bytes | None = None) -> None:
        self.messages.append(msg)


def trainers_at(knowledge: Knowledge, jobs: dict[str, TrainJob]) -> list[Trainer]:
    """The two trainers as they were at the cut."""
    return [Trainer(node, None if job is None else jobs[job], answered)
            for node, job, answered in knowledge.holding]  # fmt: skip


def check(folder: Path, knowledge: Knowledge, jobs: dict[str, TrainJob]) -> list[str]:
    """Start a coordinator on `folder` in this process, run the run to its end with the trainers
    as they were, and say what broke (nothing: [])."""
    from derl.nodes.coordinator.evolution import EvolutionPolicy
    from derl.nodes.coordinator.node import DONE_ANNOUNCEMENTS, Coordinator

    try:
        coordinator = Coordinator(RUN, folder, EvolutionPolicy(RUN, folder, config()))
    except (SystemExit, Exception) as refused:  # a refusal, or a fault
        return [f"the coordinator did not start: {refused!r}"]
    problems = _journal_holds(folder, knowledge, "at the start")
    heard = Heard()
    coordinator.bus = heard  # type: ignore[assignment]
    trainers = {t.node: t for t in trainers_at(knowledge, jobs)}
    for node in trainers:  # each holds its liveliness token
        coordinator._liveliness("trainer", node, True)
    try:
        inbox: list[MessageBase] = [t.again() for t in trainers.values()]
        after = 0  # rounds since the run finished: its serve loop goes on while it says so
        for _ in range(2000):
            after += coordinator.state.finished
            if after == DONE_ANNOUNCEMENTS:  # as the serve loop does before it ends
                coordinator.settle()
                coordinator.policy.finish()
                break
            for msg in inbox:
                coordinator._take(decode(encode(msg)))
            coordinator._assign_idle()
            coordinator.settle()
            inbox = []
            for msg in heard.messages:
                node = getattr(msg, "node", None)
                if node in trainers:
                    inbox += trainers[node].hear(msg)
            heard.messages.clear()
            if not inbox:  # nothing answered: each sends its report again or asks again
                inbox = [t.again() for t in trainers.values()]
        else:
            problems.append(f"the run did not finish: {coordinator.policy.born} born")
    finally:
        coordinator.close()
    return problems + _journal_holds(folder, knowledge, "at the end", finished=True)


def _journal_holds(folder: Path, knowledge: Knowledge, when: str, finished: bool = False
                   ) -> list[str]:  # fmt: skip
    """What the folder's journal and checkpoint files break of the invariants (see above)."""
    problems = []
    journal = list(replay(folder))
    issued = {m.job for m in journal if isinstance(m, TrainJob)}
    for job in sorted(knowledge.received - issued):
        problems.append(f"{when}: job {job}, received by a trainer, is not in the journal")
    births = Counter(m.child for m in journal if isinstance(m, Birth))
    born_from = {m.child: m.job for m in journal if isinstance(m, Birth)}
    bodies = {m.child: m.genome for m in journal if isinstance(m, Birth)}
    for child, job in knowledge.acked:
        if born_from.get(child) != job:
            problems.append(f"{when}: acknowledged birth of {child} (job {job}) is not in the "
                            f"journal (born from {born_from.get(child)})")  # fmt: skip
        elif _checkpoint(folder, child) != checkpoint_of(child, bodies[child], config().world):
            problems.append(f"{when}: acknowledged {child}'s checkpoint file is missing or not "
                            "its trainer's")  # fmt: skip
    problems += [f"{when}: {child} born {n} times" for child, n in births.items() if n > 1]
    if finished:
        total = config().total
        if len(births) != total:
            problems.append(f"{when}: {len(births)} born of {total}")
        for child in births:
            if _checkpoint(folder, child) is None:
                problems.append(f"{when}: {child} has no checkpoint file")
        if not (folder / "summary.json").is_file():
            problems.append(f"{when}: no summary.json")
        for best in sorted((folder / "best").glob("*")):
            if not (best / "checkpoint.pt").is_file():
                problems.append(f"{when}: {best.name} of the best has no checkpoint.pt")
    return problems


def _checkpoint(folder: Path, child: str) -> bytes | None:
    path = folder / "checkpoints" / f"{child}.pt"
    return path.read_bytes() if path.is_file() else None


def check_real(folder: Path, knowledge: Knowledge, jobs: dict[str, TrainJob]) -> list[str]:
    """The same with a real `derl coordinator` process and the trainers over real Zenoh."""
    from derl.nodes.runtime.processes import spawn_derl, stop_all

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    log = folder.parent / f"{folder.name}.log"
    profile = folder.parent / "crash.yaml"
    profile.write_text(yaml.safe_dump(PROFILE))
    coordinator = spawn_derl(
        ["coordinator", "--run", RUN, "--profile", str(profile), "--run-dir", str(folder),
         "--listen", endpoint], log,
    )  # fmt: skip
    problems = []
    try:
        time.sleep(0.5)
        if coordinator.poll() is not None:
            return [f"the coordinator refused to start: {log.read_text().strip()[-300:]}"]
        zenoh_trainers(endpoint, trainers_at(knowledge, jobs), None, timeout=120)
        if coordinator.wait(60) != 0:
            problems.append(f"the coordinator failed: {log.read_text().strip()[-300:]}")
    except (TimeoutError, subprocess.TimeoutExpired) as error:
        problems.append(f"{error}")
    finally:
        stop_all([coordinator])
    return problems + _journal_holds(folder, knowledge, "at the end", finished=True)


# --- 4. every cut ------------------------------------------------------------------------------


@dataclass
class Recorded:
    """A recorded run and its crash states."""

    work: Path
    ops: list[Op]
    jobs: dict[str, TrainJob]  # every job of the run, by id
    tried: Counter[str]  # states by kind
    distinct: list[Cut]  # one state of each distinct (normalized state, knowledge)
    refused: list[dict[str, object]]  # states a start refuses (a failure)
    seconds: float


def record_and_cut(work: Path) -> Recorded:
    """Record the run in `work`, then every crash state of it, normalized and told apart."""
    started = time.monotonic()
    trace = record(work)
    run_dir = work / "run"
    ops = parse_trace(trace, run_dir, work / "marks")
    jobs = {m.job: m for m in replay(run_dir) if isinstance(m, TrainJob)}
    tried: Counter[str] = Counter()
    distinct: dict[tuple[str, Knowledge], Cut] = {}
    refused = []
    scratch = work / "states"
    scratch.mkdir()
    for cut in cuts(ops, run_dir):
        tried[cut.kind] += 1
        try:
            key = (normalized(cut.state, scratch / "segment.mcap"), cut.knowledge)
        except JournalDamaged as damage:
            refused.append(_failure(cut, [f"the start refuses it: {damage}"]))
            continue
        distinct.setdefault(key, cut)
    return Recorded(work, ops, jobs, tried, list(distinct.values()), refused,
                    time.monotonic() - started)  # fmt: skip


def check_cut(recorded: Recorded, cut: Cut, real: bool = False) -> dict[str, object] | None:
    """Check one state (in this process, or with real processes); its failure, if any."""
    folder = Path(tempfile.mkdtemp(prefix="state-", dir=recorded.work))
    shutil.rmtree(folder)
    build(cut.state, folder)
    try:
        problems = (check_real if real else check)(folder, cut.knowledge, recorded.jobs)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return _failure(cut, problems, real) if problems else None


def journaled(recorded: Recorded, cut: Cut) -> list[MessageBase]:
    """The messages of a state's journal, as a start reads them (its torn tail cut)."""
    folder = Path(tempfile.mkdtemp(prefix="journal-", dir=recorded.work))
    build({k: v for k, v in cut.state.items() if k.startswith("journal")}, folder / "run")
    try:
        if found := segments(folder / "run"):
            cut_torn_tail(found[-1])
        return list(replay(folder / "run"))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def last_checkpoint_late(recorded: Recorded) -> Cut:
    """A kill just after the run's last birth was journaled, before its checkpoint file was in
    place. Which of the two the recorded run wrote first is up to its two processes' timing, so
    where the checkpoint came first the state is made from the first kill state with every birth
    journaled, less the checkpoint files of the births not yet acknowledged: what the other
    order leaves (the Ack waits for both, so the trainers' knowledge is the same)."""
    # every cut in order: `distinct` keeps a state once, under the first cut that left it
    for cut in cuts(recorded.ops, recorded.work / "run"):
        if cut.kind != "kill":
            continue
        births = {m.child for m in journaled(recorded, cut) if isinstance(m, Birth)}
        if len(births) < config().total:
            continue
        late = births - {child for child, _ in cut.knowledge.acked}
        state = {name: content for name, content in cut.state.items() if not (
            name.startswith("checkpoints/") and name[12:].split(".pt")[0] in late)}  # fmt: skip
        return Cut(cut.index, "kill", state, cut.knowledge)
    raise RuntimeError("the recorded run never journaled its last birth")


def holds_at_start(recorded: Recorded, cut: Cut) -> list[str]:
    """What a state breaks of the invariants a start must find (every job a trainer received
    and every acknowledged birth with its checkpoint in place), without running the run."""
    folder = Path(tempfile.mkdtemp(prefix="state-", dir=recorded.work))
    shutil.rmtree(folder)
    build(cut.state, folder)
    try:
        if found := segments(folder):
            cut_torn_tail(found[-1])
        return _journal_holds(folder, cut.knowledge, "at the start")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def run(work: Path, sample: int | None, real: int, seed: int = 0) -> dict[str, object]:
    started = time.monotonic()
    recorded = record_and_cut(work)
    rng = random.Random(seed)
    chosen = recorded.distinct
    if sample is not None and sample < len(chosen):
        chosen = rng.sample(chosen, sample)
    failures = list(recorded.refused)
    failures += filter(None, (check_cut(recorded, cut) for cut in chosen))
    reals = rng.sample(chosen, min(real, len(chosen)))
    failures += filter(None, (check_cut(recorded, cut, real=True) for cut in reals))
    return {
        "run": {"profile": PROFILE, "trainers": len(NODES)},
        "operations": dict(Counter(op.kind for op in recorded.ops)),
        "cut_points": len(recorded.ops) + 1,
        "states_tried": dict(recorded.tried),
        "states_tried_total": sum(recorded.tried.values()),
        "distinct_states": len(recorded.distinct),
        "checked_in_process": len(chosen),
        "checked_with_a_real_coordinator": len(reals),
        "failed": len(failures),
        "failures": failures[:20],
        "recorded_and_cut_in_s": round(recorded.seconds, 1),
        "seconds": round(time.monotonic() - started, 1),
    }


def _failure(cut: Cut, problems: list[str], real: bool = False) -> dict[str, object]:
    return {"cut": cut.index, "kind": cut.kind, "torn_at": cut.torn_at, "real": real,
            "problems": problems[:5]}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sample", type=int, help="check this many distinct states, not all")
    parser.add_argument("--real", type=int, default=3, help="states checked with real processes")
    parser.add_argument("--work", help="folder (default: a temporary one, removed)")
    parser.add_argument("--record-in", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    import logging

    logging.basicConfig(level=logging.ERROR)
    if args.record_in:
        return _record_run(args.record_in)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="derl-crash-"))
    try:
        print(json.dumps(run(work / "crash", args.sample, args.real), indent=2))
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
