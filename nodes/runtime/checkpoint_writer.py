"""The process that writes the coordinator's checkpoint files: `python -I checkpoint_writer.py
FOLDER`, started by `CheckpointFiles` (the file, not the module: it imports msgpack, not derl).

A batch's files are written to temporary names, put on the disk with one `syncfs` of the file
system (Linux; elsewhere one fsync per file), renamed into place, links made to files already in
place, and the folder fsynced once: a file that exists is whole, and once the answer says a file
is written it survives a power loss.

It is a process of its own so that its system calls never wait for the coordinator's
interpreter lock. In a thread beside the coordinator's busy loop, every system call (six per
file) gave the lock up and then waited for it, up to a switch interval; at a thousand births a
second the writer thread was busy all the time and an Ack waited ~1 s for its file (measured
with `bench/bus.py`, 1,000 simulated workers).

Its input is a msgpack stream of batches, each a map agent -> the checkpoint (bytes) or the
agent whose file it shares (str); for each batch it answers agent -> None (written) or
[errno, message]. It runs in a process group of its own and ignores SIGINT and SIGTERM: a
terminal's Ctrl-C or a launcher's SIGTERM reaches a process group, and one that ended it, even
while it starts, lost the checkpoints of births the coordinator had journaled already (a run
resumed after a Ctrl-C then waited for a file nobody could write). It ends at the end of its
input: when the coordinator closes it or dies (an answer that finds the coordinator gone ends it
too, quietly: nobody waits for it)."""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import cast

import msgpack

Batch = dict[str, bytes | str]
READ_SIZE = 1 << 20
MAX_MESSAGE = (1 << 31) - 1


def _find_syncfs() -> Callable[[int], int] | None:
    """Linux's syncfs(2) (every dirty file of one file system onto the disk), if there is one."""
    name = ctypes.util.find_library("c")
    libc = ctypes.CDLL(name, use_errno=True) if name else None
    return getattr(libc, "syncfs", None)


_syncfs = _find_syncfs()


def write_batch(
    folder: Path, batch: Batch, syncfs: Callable[[int], int] | None = _syncfs
) -> dict[str, OSError | None]:
    """Write `batch` into `folder` (with one `syncfs`, or one fsync per file if None); each
    agent's error, or None. One bad file fails alone."""
    data = {agent: what for agent, what in batch.items() if isinstance(what, bytes)}
    sources = {agent: what for agent, what in batch.items() if isinstance(what, str)}
    failures = {agent: _write_file(folder, agent, checkpoint) for agent, checkpoint in data.items()}
    complete = [agent for agent in data if failures[agent] is None]
    try:
        _sync(folder, [_tmp(folder, agent) for agent in complete], syncfs)
    except OSError as error:
        failures |= dict.fromkeys(complete, error)
    for agent in [*data, *sources]:  # links once the files they share are in place
        failed = failures[agent] if agent in data else _link_file(folder, agent, sources[agent])
        if failed is None:
            try:
                os.replace(_tmp(folder, agent), path(folder, agent))
            except OSError as error:
                failed = error
        failures[agent] = failed
    written = [agent for agent, failed in failures.items() if failed is None]
    if written:
        try:
            _fsync(folder)
        except OSError as error:
            failures |= dict.fromkeys(written, error)
    return failures


def path(folder: Path, agent: str) -> Path:
    return folder / f"{agent}.pt"


def _tmp(folder: Path, agent: str) -> Path:
    return folder / f"{agent}.pt.tmp"


def _write_file(folder: Path, agent: str, checkpoint: bytes) -> OSError | None:
    """The temporary file of `agent` (not yet synced); the error, if any."""
    try:
        fd = os.open(_tmp(folder, agent), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(fd, checkpoint)
        finally:
            os.close(fd)
    except OSError as error:
        return error
    return None


def _link_file(folder: Path, agent: str, source: str) -> OSError | None:
    """The temporary file of `agent`, a link to `source`'s file; the error, if any."""
    try:
        _tmp(folder, agent).unlink(missing_ok=True)
        _tmp(folder, agent).hardlink_to(path(folder, source))
    except OSError as error:
        return error
    return None


def _sync(folder: Path, files: list[Path], syncfs: Callable[[int], int] | None) -> None:
    """`files` (written, not yet renamed) onto the disk: one syncfs, or one fsync each."""
    if not files:
        return
    if syncfs is None:
        for file in files:
            _fsync(file)
        return
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        if syncfs(fd) != 0:
            error = ctypes.get_errno()
            raise OSError(error, os.strerror(error), str(folder))
    finally:
        os.close(fd)


def _fsync(file: Path) -> None:
    fd = os.open(file, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def messages(fd: int) -> Iterator[object]:
    """The msgpack messages read from `fd`, until its end."""
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=MAX_MESSAGE)
    while chunk := os.read(fd, READ_SIZE):
        unpacker.feed(chunk)
        yield from unpacker


def send(fd: int, message: object) -> None:
    _write_all(fd, msgpack.packb(message, use_bin_type=True))


def main() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    folder = Path(sys.argv[1])
    try:
        for batch in messages(sys.stdin.fileno()):
            failures = write_batch(folder, cast(Batch, batch))
            send(sys.stdout.fileno(), {
                agent: None if error is None else [error.errno, str(error)]
                for agent, error in failures.items()
            })  # fmt: skip
    except BrokenPipeError:
        return


if __name__ == "__main__":
    main()
