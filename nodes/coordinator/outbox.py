"""The coordinator's outbox: what a group of messages made it say, released for publishing once
that group is on disk, by a thread of its own, so the loop handles the next group while the disk
syncs.

The loop journals a group, writes it into the journal file and hands its replies here (`send`).
The syncer thread takes every group waiting as one batch, fsyncs the journal once (a later
group's writes may ride along: fsync covers whatever the file holds) and releases the replies in
order; the loop takes them (`take`) and publishes them. A reply that waits for a checkpoint file
(a Birth and an Ack go out only once the agent's checkpoint is on disk: `Ledger.save`, whose
future waits through a failed write until the file is written again) is released when that write
is done, so the jobs of a group never wait behind a report's file.

So nothing is seen that a crash, even a power loss, could forget, the loop never waits for the
disk, and the loop alone touches the bus: a publish hands the interpreter lock over, which costs
little when no other thread wants it (measured at 1,000 simulated workers: fsync and checkpoint
waits were a quarter of the loop's time; publishing from a second thread made each publish wait
~0.3 ms for the lock). This thread pays that price itself: after each fsync it waits for the lock
behind the busy loop, a switch interval (5 ms) or more when other threads wait too (measured: the
fsync takes p99 0.5 ms on the disk and 13-14 ms as this thread sees it; a shorter interval moved
the wait to the loop).

A sync that fails (the journal could not be written: `fault`) holds every reply from then on,
released in order by `resume` once the journal is written again (`Journal.recover`); the
coordinator's loop waits meanwhile (`Ledger.stalled`). Any other fault of the thread's own stops
the coordinator: `send` raises it from then on (a thread that died instead would leave the loop
running with nothing ever released: workers waiting for ever), and `drain` no longer waits.
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future

from derl.messages import MessageBase

log = logging.getLogger("derl.coordinator")

Reply = tuple[MessageBase, bytes, Future[None] | None]
"""A message, its encoding, and the checkpoint write it waits for (if any)."""


class Outbox:
    def __init__(self, sync: Callable[[], None]) -> None:
        """`sync` puts the journal file's contents on the disk (OSError if it cannot)."""
        self._sync = sync
        self._groups: queue.SimpleQueue[list[Reply] | None] = queue.SimpleQueue()
        self._released: queue.SimpleQueue[list[tuple[MessageBase, bytes]]] = queue.SimpleQueue()
        self._idle = threading.Condition()
        self._pending = 0  # replies handed over, neither released nor dropped yet
        self._lock = threading.Lock()  # `fault` and `_held`
        self._held: list[Reply] = []  # replies held while the journal cannot be written
        self.fault: OSError | None = None
        """Why the journal could not be synced; every reply is held until `resume`."""
        self.failure: Exception | None = None
        self.released = threading.Event()
        """Set when replies are released (the loop may wait on it instead of sleeping)."""
        self._thread = threading.Thread(target=self._run, name="outbox", daemon=True)
        self._thread.start()

    def send(self, group: list[Reply]) -> None:
        """Release `group` once the journal file's contents written so far are on the disk."""
        if self.failure is not None:
            raise self.failure
        self._count(len(group))
        self._groups.put(group)

    def take(self) -> list[tuple[MessageBase, bytes]]:
        """The replies released so far, in order: to publish now."""
        replies: list[tuple[MessageBase, bytes]] = []
        while not self._released.empty():
            replies += self._released.get()
        return replies

    def drain(self, until: Callable[[], bool] = lambda: False) -> None:
        """Wait until every reply handed over is released or dropped (or held by a fault), or
        `until()` is true (checked again on `wake`)."""
        with self._idle:
            self._idle.wait_for(lambda: self._pending <= 0 or self.fault is not None or until())

    def wake(self) -> None:
        """Have `drain` check its `until` again."""
        with self._idle:
            self._idle.notify_all()

    def resume(self) -> None:
        """The journal is written again, every message held for on the disk: release what was
        held, in order, and sync as before."""
        with self._lock:
            held, self._held, self.fault = self._held, [], None
        self._deliver(held)

    def close(self) -> None:
        """Release what is waiting, then stop the thread; closing twice is harmless."""
        if self._thread.is_alive():
            self._groups.put(None)
            self._thread.join()
        with self._lock:  # never to be published: the coordinator stops
            held, self._held = self._held, []
        self._count(-len(held))

    def _run(self) -> None:
        done = False
        while not done:
            batch: list[list[Reply]] = []
            group = self._groups.get()
            while group is not None:
                batch.append(group)
                try:
                    group = self._groups.get_nowait()
                except queue.Empty:
                    break
            done = group is None
            try:
                self._release(batch)
            except Exception as error:  # a fault of its own: nothing may be seen, and the loop
                # stops on it (`send`) rather than stall
                log.critical("the outbox failed (nothing more is published): %r", error)
                self._fail(error)

    def _fail(self, error: Exception) -> None:
        """Nothing more is released: `send` raises `error` from now on, and `drain` returns."""
        if self.failure is None:
            self.failure = error
        with self._idle:
            self._pending = 0
            self._idle.notify_all()

    def _count(self, change: int) -> None:
        with self._idle:
            self._pending += change
            if self._pending <= 0:
                self._idle.notify_all()

    def _release(self, batch: list[list[Reply]]) -> None:
        replies = [reply for group in batch for reply in group]
        if not replies or self.failure is not None:
            return  # after a failure, dropped (`_fail` let `drain` return)
        with self._lock:
            if self.fault is not None:
                self._held += replies
                return
        try:
            self._sync()
        except OSError as error:  # the journal cannot be written: held until `resume`
            with self._lock:
                self._held += replies
                self.fault = error
            with self._idle:
                self._idle.notify_all()
            return
        self._deliver(replies)

    def _deliver(self, replies: list[Reply]) -> None:
        """Release `replies`, on the disk: those that wait for a checkpoint file once it is."""
        # the group's own replies first: a checkpoint written already runs its callback at once,
        # and its Ack must not overtake the Birth journaled before it
        self._publishable([(msg, data) for msg, data, after in replies if after is None])
        for msg, data, after in replies:
            if after is not None:
                after.add_done_callback(functools.partial(self._written, msg=msg, data=data))

    def _written(self, done: Future[None], msg: MessageBase, data: bytes) -> None:
        """A reply's checkpoint write is over: released, or dropped if it failed (the ledger
        writes the file again, and the trainer sends its report again)."""
        if done.exception() is None:
            self._publishable([(msg, data)])
        else:
            self._count(-1)

    def _publishable(self, replies: list[tuple[MessageBase, bytes]]) -> None:
        if replies:
            self._released.put(replies)
            self.released.set()
            self._count(-len(replies))
