"""A run directory's crash states, from a trace of the writes of a run (strace's): the
operations, a model of the disk, and the state a kill or a power cut leaves after each one.

The model (`Disk`): the run directory after each operation, twice: as a process kill leaves it
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
state). Each state comes with what the trainers knew then (`Knowledge`: their marks in the
trace).
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from derl.nodes.journal.segments import cut_torn_tail


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
            fd, path, position = match.groups()
            positions[(fd, path)] = int(position)
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
            positions.pop((match[1], match[2]), None)
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
            content = self.content(op.path)
            del content[op.size :]
            content.extend(bytes(op.size - len(content)))
        elif op.kind == "write":
            content = self.content(op.path)
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

    def content(self, path: str) -> bytearray:
        """The data of file `path` now (the page cache)."""
        inode = self.names[path]
        if inode is DIR:
            raise IsADirectoryError(path)
        return self.data[inode]

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


def cuts(ops: list[Op], run_dir: Path, nodes: tuple[str, ...]) -> Iterator[Cut]:
    """Every crash state of the run recorded in `ops` (whose files are in `run_dir` now), its
    trainers `nodes` (see the module's docstring)."""
    disk = Disk()
    holding: dict[str, tuple[str | None, bool]] = {node: (None, True) for node in nodes}
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
            done = bytes(disk.content(op.path)[: op.offset])  # the writes before it
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


def build(state: dict[str, bytes | None], folder: Path) -> None:
    """Make `state` in `folder`, a new folder."""
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
