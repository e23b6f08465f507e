"""The coordinator's checkpoint files (`<run dir>/checkpoints/<agent>.pt`), written beside its loop.

A born agent's policy comes inside its FitnessReport. `save` hands it to a writer thread and
returns a future that completes once the file is whole on the disk (the coordinator acknowledges
a report only then). A body born as a repeat of an earlier one (the same body, so the same
training) gets the earlier one's file as its own, a hard link made after the batch's files are in
place (`link`), so `checkpoints/<agent>.pt` holds every born agent's policy. A link whose source's
file is not there (a crash lost it before the source's report was acknowledged) waits until that
file is written from the re-sent report.

Group commit, as the journal's: the writer thread takes every checkpoint waiting as one batch and
sends it to a writer process (`checkpoint_writer`: temporary files, one `syncfs`, renames, one
fsync of the folder), so a batch costs two waits for the disk whatever its size and few system
calls of this process (a pipe takes up to 64 KiB a call): each one hands the interpreter lock
over, and at a thousand births a second those hand-overs, not the disk, held the Acks back.
The process starts with the first batch; if it dies, that batch's futures fail (a report is
acknowledged once its file is written from the trainer's re-sent report) and the next batch
starts a new one.
"""

from __future__ import annotations

import queue
import subprocess
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import Future
from pathlib import Path
from typing import IO, cast

from derl.nodes.runtime import checkpoint_writer

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
        self._process = WriterProcess(self.folder)
        self._unlinked: dict[str, list[tuple[str, Future[None]]]] = {}  # source -> links waiting
        # for its file (the writer thread's)
        self._writer = threading.Thread(target=self._run, name="checkpoints", daemon=True)
        self._writer.start()

    def path(self, agent: str) -> Path:
        return checkpoint_writer.path(self.folder, agent)

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
        for source, links in self._unlinked.items():
            for _, future in links:
                future.set_exception(FileNotFoundError(f"{self.path(source)} was never written"))
        self._process.close()

    def _write(self, batch: list[Item]) -> None:
        """One batch, each agent once (its report re-sent while the file was written), with the
        links that waited for a file the batch writes."""
        items: checkpoint_writer.Batch = {}
        waiting: dict[str, list[Future[None]]] = {}
        for agent, what, future in batch:
            if future.set_running_or_notify_cancel():
                items.setdefault(agent, what)
                waiting.setdefault(agent, []).append(future)
        for source in [agent for agent, what in items.items() if isinstance(what, bytes)]:
            for agent, future in self._unlinked.pop(source, []):
                items.setdefault(agent, source)
                waiting.setdefault(agent, []).append(future)
        if not waiting:
            return
        failures = self._process.write(items)
        for agent, futures in waiting.items():
            what = items[agent]
            if isinstance(what, str) and not self.path(what).exists():
                # its source's file is not there yet (a crash lost it, and the source's trainer
                # sends its report again): linked when that file is written
                self._unlinked.setdefault(what, []).extend((agent, f) for f in futures)
                continue
            for future in futures:
                if failures[agent] is None:
                    future.set_result(None)
                else:
                    future.set_exception(failures[agent])


class WriterProcess:
    """The `checkpoint_writer` process of one folder, started when first needed."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.process: subprocess.Popen[bytes] | None = None
        self.answers: Iterator[object] = iter(())  # the process's answers, one per batch

    def write(self, batch: checkpoint_writer.Batch) -> dict[str, OSError | None]:
        """Each agent's error, or None; raises OSError if the process failed (it is ended, the
        next call starts another)."""
        if self.process is None:
            self.process = subprocess.Popen(
                # the file itself, isolated (-I): only msgpack to import, not derl (0.2 s of CPU)
                [sys.executable, "-I", checkpoint_writer.__file__, str(self.folder)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                process_group=0,  # a signal to the coordinator's group must not end it
            )
            self.answers = checkpoint_writer.messages(_pipe(self.process.stdout).fileno())
        try:
            checkpoint_writer.send(_pipe(self.process.stdin).fileno(), batch)
            answer = cast(dict[str, list | None], next(self.answers))
        except (OSError, StopIteration):
            code = self.close()
            raise OSError(f"the checkpoint writer process ended (exit code {code})") from None
        return {agent: _error(answer[agent]) for agent in batch}

    def close(self, timeout: float = 30.0) -> int | None:
        """End the process once it has written what it was given; its exit code."""
        process, self.process = self.process, None
        if process is None:
            return None
        _pipe(process.stdin).close()
        try:
            code = process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            code = process.wait()
        _pipe(process.stdout).close()
        return code


def _pipe(pipe: IO[bytes] | None) -> IO[bytes]:
    """A pipe of the writer process, which is started with both (`subprocess.PIPE`)."""
    assert pipe is not None
    return pipe


def _error(answer: list | None) -> OSError | None:
    if answer is None:
        return None
    error = OSError(answer[1])
    error.errno = answer[0]
    return error
