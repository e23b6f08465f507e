"""The coordinator's checkpoint files (`<run dir>/checkpoints/<agent>.pt`), written beside its loop.

A born agent's policy comes inside its FitnessReport. A writer thread writes it to a temporary
file, puts it on the disk, renames it into place and syncs the folder, so a file that exists is
whole and a file whose future has completed survives a power loss. `save` returns that future;
the coordinator acknowledges a report only once it is done.

A body born as a repeat of an earlier one (the same body, so the same training) gets the earlier
one's file as its own, a hard link made by the same writer after the batch's files are in place
(`link`), so `checkpoints/<agent>.pt` holds every born agent's policy.

Group commit, as the journal's: the writer takes every checkpoint waiting for it as one batch,
writes the files, puts them on the disk with one `syncfs` of the file system (Linux; elsewhere
one fsync per file), renames them and fsyncs the folder once. So a batch costs two waits for the
disk whatever its size, and few system calls: each one hands the interpreter lock over, and at a
thousand births a second those hand-overs, not the disk, were what slowed the coordinator
(measured with `bench/bus.py`: 8 threads fsyncing one file each kept it near 800 assignments/s).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path

FOLDER = "checkpoints"

Item = tuple[str, bytes | str, Future[None]]


class CheckpointFiles:
    def __init__(self, run_dir: Path) -> None:
        self.folder = Path(run_dir) / FOLDER
        self.folder.mkdir(parents=True, exist_ok=True)
        # (agent, its checkpoint or the agent whose file it shares, future)
        self._waiting: queue.SimpleQueue[Item | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._closed = False
        self._writer = threading.Thread(target=self._run, name="checkpoints", daemon=True)
        self._writer.start()

    def path(self, agent: str) -> Path:
        return self.folder / f"{agent}.pt"

    def save(self, agent: str, checkpoint: bytes) -> Future[None]:
        """Write `agent`'s checkpoint in the background; the future says when it is on disk
        (or why it is not)."""
        return self._put(agent, checkpoint)

    def link(self, agent: str, source: str) -> Future[None]:
        """Make `source`'s file (saved before, or by an earlier `save`) `agent`'s too, in the
        background; the future says when the link is on disk (or why it is not)."""
        return self._put(agent, source)

    def _put(self, agent: str, what: bytes | str) -> Future[None]:
        future: Future[None] = Future()
        with self._lock:
            if self._closed:
                raise RuntimeError("checkpoint files closed")
            self._waiting.put((agent, what, future))
        return future

    def close(self) -> None:
        """Wait for the writes under way; closing twice is harmless."""
        with self._lock:
            if not self._closed:
                self._closed = True
                self._waiting.put(None)
        self._writer.join()

    # --- the writer thread -------------------------------------------------------------------

    def _run(self) -> None:
        done = False
        while not done:
            item = self._waiting.get()
            batch = []
            while item is not None:
                batch.append(item)
                try:
                    item = self._waiting.get_nowait()
                except queue.Empty:
                    break
            else:
                done = True
            try:
                self._write(batch)
            except BaseException as error:  # never leave a future waiting for ever
                for _, _, future in batch:
                    if not future.done():
                        future.set_exception(error)

    def _write(self, batch: list[Item]) -> None:
        """One batch: the files' data onto the disk before their renames, the links once the
        renames are made, and the folder's entries onto the disk before any future completes."""
        data: dict[str, bytes] = {}
        sources: dict[str, str] = {}
        waiting: dict[str, list[Future[None]]] = {}
        for agent, what, future in batch:
            if not future.set_running_or_notify_cancel():
                continue
            # the same agent twice (its report re-sent while the file was written): once
            if agent in waiting:
                pass
            elif isinstance(what, bytes):
                data[agent] = what
            else:
                sources[agent] = what
            waiting.setdefault(agent, []).append(future)
        if not waiting:
            return
        failures = {agent: self._write_file(agent, data[agent]) for agent in data}
        complete = [agent for agent in data if failures[agent] is None]
        try:
            self._sync([self._tmp(agent) for agent in complete])
        except OSError as error:
            failures |= dict.fromkeys(complete, error)
        written: dict[str, list[Future[None]]] = {}
        for agent in [*data, *sources]:  # links once the files they share are in place
            failed = failures[agent] if agent in data else self._link_file(agent, sources[agent])
            if failed is None:
                try:
                    self._tmp(agent).replace(self.path(agent))
                except OSError as error:
                    failed = error
            if failed is None:
                written[agent] = waiting[agent]
            else:
                for future in waiting[agent]:
                    future.set_exception(failed)
        if not written:
            return
        try:
            _fsync(self.folder)
        except OSError as error:
            for futures in written.values():
                for future in futures:
                    future.set_exception(error)
            return
        for futures in written.values():
            for future in futures:
                future.set_result(None)

    def _sync(self, files: list[Path]) -> None:
        """`files` (written, not yet renamed) onto the disk: one syncfs, or one fsync each."""
        if not files:
            return
        if _syncfs is None:
            for file in files:
                _fsync(file)
            return
        folder = os.open(self.folder, os.O_RDONLY | os.O_DIRECTORY)
        try:
            if _syncfs(folder) != 0:
                error = ctypes.get_errno()
                raise OSError(error, os.strerror(error), str(self.folder))
        finally:
            os.close(folder)

    def _tmp(self, agent: str) -> Path:
        return self.folder / f"{agent}.pt.tmp"

    def _write_file(self, agent: str, checkpoint: bytes) -> OSError | None:
        """The temporary file of `agent` (not yet synced); the error, if any."""
        try:
            self._tmp(agent).write_bytes(checkpoint)
        except OSError as error:
            return error
        return None

    def _link_file(self, agent: str, source: str) -> OSError | None:
        """The temporary file of `agent`, a link to `source`'s file; the error, if any."""
        try:
            self._tmp(agent).unlink(missing_ok=True)
            self._tmp(agent).hardlink_to(self.path(source))
        except OSError as error:
            return error
        return None


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _find_syncfs() -> Callable[[int], int] | None:
    """Linux's syncfs(2) (every dirty file of one file system onto the disk), if there is one."""
    name = ctypes.util.find_library("c")
    libc = ctypes.CDLL(name, use_errno=True) if name else None
    return getattr(libc, "syncfs", None)


_syncfs = _find_syncfs()
