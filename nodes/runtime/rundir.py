"""A run directory's lock (one coordinator at a time) and whole-or-nothing file writes.

`lock_run_dir` holds an OS lock (``flock`` on ``RUN_DIR/.lock``, which names the holder's pid and
host) while a coordinator runs; the kernel drops it when the process ends, however it ends, so a
crashed coordinator never leaves a stale lock. `write_atomic` and `sync_folder` are
`derl.files`' (whole-or-nothing writes, which derl's own files use too), named here for the nodes.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import socket
from collections.abc import Iterator
from pathlib import Path

from derl.files import sync_folder as sync_folder
from derl.files import write_atomic as write_atomic
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
