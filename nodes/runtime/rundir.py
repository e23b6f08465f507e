"""A run directory's lock (one coordinator at a time) and whole-or-nothing file writes.

`lock_run_dir` holds an OS lock (``flock`` on ``RUN_DIR/.lock``, which names the holder's pid and
host) while a coordinator runs; the kernel drops it when the process ends, however it ends, so a
crashed coordinator never leaves a stale lock. `write_atomic` writes a temporary file in the same
folder, syncs it, renames it over the target and syncs the folder: a reader, or a restart after a
crash or power loss, finds the old file or the new one, never a part.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import socket
import uuid
from collections.abc import Iterator
from pathlib import Path

from derl.nodes.errors import InUse

LOCK_FILE = ".lock"


class RunDirLocked(InUse):
    """Another process holds the run directory's lock."""


@contextlib.contextmanager
def lock_run_dir(run_dir: Path) -> Iterator[None]:
    """Hold `run_dir`'s lock for the `with` block; `RunDirLocked` (naming the holder) if it is
    held already. The directory is created if missing."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(run_dir / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise
            raise RunDirLocked(f"{run_dir} is in use by {_holder(fd)}") from None
        holder = json.dumps({"pid": os.getpid(), "host": socket.gethostname()}).encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, holder + b"\n", 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def _holder(fd: int) -> str:
    """Who holds the lock, as its file says (it may not have written it yet)."""
    try:
        holder = json.loads(os.pread(fd, 4096, 0))
        return f"a coordinator with pid {int(holder['pid'])} on host {holder['host']}"
    except (ValueError, KeyError, TypeError):
        return "another process (its pid and host are not written yet)"


def write_atomic(path: Path, data: str | bytes) -> None:
    """Replace `path` by `data` (text as UTF-8) in one step that a crash cannot leave half done."""
    path = Path(path)
    content = data.encode() if isinstance(data, str) else data
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(content)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    sync_folder(path.parent)


def sync_folder(folder: Path) -> None:
    """Put `folder`'s entries (the files and folders created, renamed or removed in it) on the
    disk: an fsync of a file does not, and a power loss can lose a file whose data was synced."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
