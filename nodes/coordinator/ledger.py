"""The coordinator's ledger: its state, the journal that rebuilds it, and every message committed.

Opening a ledger replays the run directory's journal into the state (only what the state knows:
`JobBook.known`; `Refused` if the journal is damaged or another run's), then opens a new
journal segment and the checkpoint files. From then on everything the coordinator accepts or says
is committed here: appended to the journal, applied to the state (the same handlers that rebuilt
it) and, if it is to be published, kept as a reply of the current group. `flush` writes the group
into the journal file and hands its replies to the `Outbox`, which releases them once the file is
on the disk (an Ack also waits for its report's checkpoint file); the node loop publishes what was
released. Acknowledging, rejecting and counting rejections are here too: each is a committed
message.

A checkpoint file is written by `save` (or `link`, a repeat's), whose future completes once the
file is on the disk: a Birth and an Ack are released only then, so a monitor that loads a born
agent's checkpoint finds it. A journal or a checkpoint file that cannot be written (a full disk,
an I/O error) makes the ledger `stalled`: nothing more is released (what waits for a file that
failed is held, the file's future still pending), the loop commits nothing and tries `recover`
every second, which writes what was not on the disk (the journal's messages into a new segment,
the checkpoints kept in memory into their files) and releases what was held; the trainers'
re-sent reports are then acknowledged. What failed, and that it works again, is said once a
minute (`DiskFaults`).

A refusal (a Reject, a Rejection) is journaled for the first `JOURNALED_REFUSALS` a minute of its
sender's identity; the rest are counted (`RunStatus.rejected`) and a Reject is still published,
so a certificate that floods refused messages cannot grow the journal without bound.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path

from derl.messages import (
    Ack,
    EvalResult,
    FitnessReport,
    MessageBase,
    Reject,
    Rejection,
    encode,
)
from derl.nodes.coordinator.disk_faults import DiskFaults
from derl.nodes.coordinator.jobs import JobBook
from derl.nodes.coordinator.outbox import Outbox, Reply
from derl.nodes.coordinator.run.audits import incarnation
from derl.nodes.errors import Refused
from derl.nodes.journal.segments import Journal, JournalDamaged, replay, segments
from derl.nodes.runtime.checkpoints import CheckpointFiles
from derl.nodes.runtime.ratelimit import FLOOD

log = logging.getLogger("derl.coordinator")

STALLED = (
    "the coordinator acknowledges nothing more and waits, the run's state kept, trying every "
    "second to write it again"
)
CHECKPOINT_WAIT_S = 30.0  # the longest `recover` waits for a checkpoint file written again
JOURNALED_REFUSALS = 60  # refusals of one sender's identity journaled per `REFUSALS_S`; the
REFUSALS_S = 60.0  # rest are counted and answered, not journaled: a flood cannot fill the disk


class Ledger:
    """`state` rebuilt from `run_dir`'s journal, and the way every later change is made; `clock`
    times the refusals' windows and the disk faults' reminders."""

    def __init__(
        self,
        run: str,
        run_dir: Path,
        state: JobBook,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.run, self.state, self.clock = run, state, clock
        self.replayed = 0
        if segments(run_dir):
            try:
                for msg in replay(run_dir):
                    if state.known(msg):  # what it decides live is known
                        state.apply(msg)
                        self.replayed += 1
            except JournalDamaged as damage:
                raise Refused(str(damage)) from None
        if state.run not in (None, run):  # its own messages would not change the state
            raise Refused(f"{run_dir} holds the journal of run {state.run!r}, not {run!r}: "
                          f"resume it with --run {state.run}")  # fmt: skip
        self.journal = Journal(run_dir)
        self.checkpoints = CheckpointFiles(run_dir)
        self.replies: list[Reply] = []  # the group's: published once it is on disk
        self.faults = DiskFaults(clock=clock)
        self.outbox = Outbox(self.journal.sync)
        self._lock = threading.Lock()  # `unwritten`, changed by the checkpoint writer's thread
        # agent -> its checkpoint (or the agent whose file it shares), whose file failed, and the
        # futures that wait for it (completed once `recover` writes it)
        self.unwritten: dict[str, tuple[bytes | str, list[Future[None]]]] = {}
        self._writing = 0  # checkpoint writes under way
        self._recovered: list[str] = []  # what `recover` wrote again since writing failed
        self.rejected = 0  # messages refused, counted for `RunStatus`
        self.unjournaled = 0  # refusals over an identity's share, counted only
        self._refusals: dict[str, tuple[float, int]] = {}  # identity -> (window start, count)

    @property
    def stalled(self) -> bool:
        """The journal or a checkpoint file cannot be written: nothing is released until
        `recover` works."""
        return (
            self.journal.failure is not None
            or self.outbox.fault is not None
            or bool(self.unwritten)
        )

    def recover(self) -> bool:
        """Write the journal again (`Journal.recover`) and release what was held, then write the
        checkpoints that failed; whether it all worked (if not, it is said once a minute)."""
        failure = self.journal.failure  # what stalled it (the first time, the first failure)
        rewritten = self.journal.recover()
        if rewritten is None:
            assert failure is not None
            self.faults.failed(failure.path, failure.error, STALLED)
            return False
        if failure is not None:
            segment = self.journal.segment.name
            self._recovered.append(f"the journal goes on in {segment} ({rewritten} messages "
                                   "not on the disk written into it)")  # fmt: skip
        self.outbox.resume()
        with self._lock:
            unwritten = {agent: what for agent, (what, _) in self.unwritten.items()}
        for agent, what in unwritten.items():
            try:
                self._write_file(agent, what).result(timeout=CHECKPOINT_WAIT_S)
            except Exception as error:
                self.faults.failed(self.checkpoints.path(agent), error, STALLED)
                return False
            self._written(agent)
            self._recovered.append(f"{self.checkpoints.path(agent).name} written")
        self.faults.works(", ".join(self._recovered))
        self._recovered = []
        return True

    def save(self, agent: str, checkpoint: bytes) -> Future[None]:
        """Write `agent`'s checkpoint file (`CheckpointFiles.save`); the future completes once it
        is on the disk. If writing fails, the ledger is stalled and keeps the bytes: the future
        completes when `recover` writes them (it never fails: what waits for it is held)."""
        return self._durable(agent, checkpoint)

    def link(self, agent: str, source: str) -> Future[None]:
        """Make `source`'s file `agent`'s too (a repeat's: `CheckpointFiles.link`), as `save`."""
        return self._durable(agent, source)

    def drain(self) -> None:
        """Wait until every reply handed to the outbox is released, or the ledger is stalled
        with no checkpoint write under way (what waits for the disk is held until `recover`)."""
        self.outbox.drain(until=lambda: self.stalled and not self._writing)

    def _write_file(self, agent: str, what: bytes | str) -> Future[None]:
        if isinstance(what, bytes):
            return self.checkpoints.save(agent, what)
        return self.checkpoints.link(agent, what)

    def _durable(self, agent: str, what: bytes | str) -> Future[None]:
        durable: Future[None] = Future()
        with self._lock:
            self._writing += 1
        self._write_file(agent, what).add_done_callback(
            lambda done: self._attempted(agent, what, durable, done)
        )
        return durable

    def _attempted(
        self, agent: str, what: bytes | str, durable: Future[None], done: Future[None]
    ) -> None:
        """A write of `agent`'s file is over: `durable` completes, or waits for `recover`."""
        error = done.exception()
        if error is None:
            self._written(agent)  # what waited longer first
            durable.set_result(None)
            with self._lock:
                self._writing -= 1
            return
        with self._lock:
            self._writing -= 1
            waiting = self.unwritten.get(agent, (what, []))[1]
            self.unwritten[agent] = (what, [*waiting, durable])
        self.faults.failed(self.checkpoints.path(agent), error, STALLED)
        self.outbox.wake()  # a `drain` waits no more

    def _written(self, agent: str) -> None:
        """`agent`'s file is on the disk: what waited for an earlier failed write of it too."""
        with self._lock:
            _, waiting = self.unwritten.pop(agent, (b"", []))
        for future in waiting:
            future.set_result(None)

    def commit(
        self, msg: MessageBase, publish: bool = True, after: Future[None] | None = None
    ) -> None:
        """Journal and apply; what the coordinator says is published once the group is on disk
        (and `after` is done, and not if it failed)."""
        data = encode(msg)
        self.journal.write(msg, data=data, flush=False)
        self.state.apply(msg)
        if publish:
            self.replies.append((msg, data, after))

    def send(self, msg: MessageBase, after: Future[None] | None = None) -> None:
        """Publish a message that is not journaled (status, a job order sent again) in order
        after the group before it (and once `after` is done, and not if it failed)."""
        self.replies.append((msg, encode(msg), after))

    def flush(self) -> None:
        """The group's messages into the journal file; its replies are released once the file
        is on the disk (`Outbox`)."""
        if not self.replies and not self.journal.pending:
            return
        self.journal.flush()
        self.outbox.send(self.replies)
        self.replies = []

    def ack(
        self, msg: FitnessReport | EvalResult, agent: str, after: Future[None] | None = None
    ) -> None:
        ack = Ack(run=self.run, of=msg.type, job=msg.job, agent=agent, node=msg.node)
        self.commit(ack, after=after)

    def answer_again(
        self, msg: FitnessReport | EvalResult, agent: str, after: Future[None] | None = None
    ) -> None:
        """Acknowledge once more a result taken already (its sender missed the Ack, or floods
        copies of it): published, not journaled, so copies do not grow the journal; its log
        line is rate-limited as warnings are."""
        log.info("%s already taken: a repeated %s from %s acknowledged", agent, msg.type,
                 msg.node, extra=FLOOD)  # fmt: skip
        self.send(Ack(run=self.run, of=msg.type, job=msg.job, agent=agent, node=msg.node), after)

    def reject(self, msg: FitnessReport | EvalResult, agent: str, reason: str) -> None:
        """Refuse a result for good: journaled, counted, and the sender told to drop it."""
        self.rejected += 1
        what = "fitness" if isinstance(msg, FitnessReport) else "evaluation"
        log.warning("rejected %s of %s from %s: %s", what, agent, msg.node, reason)
        reject = Reject(
            run=self.run, of=msg.type, job=msg.job, agent=agent, node=msg.node, reason=reason
        )
        if self._journal_refusal(msg.node):
            self.commit(reject)
        else:
            self.send(reject)

    def never_issued(self, msg: FitnessReport | EvalResult, agent: str, also: str = "") -> None:
        """Reject a result of a job its sender was never given for `agent`."""
        self.reject(msg, agent, f"job {msg.job} was never issued to {msg.node} for "
                    f"{agent}{also}")  # fmt: skip

    def rejection(
        self, why: str, key: str, msg: MessageBase | None = None, sender: str | None = None
    ) -> None:
        """Journal (unpublished) and count a message refused before any handler took it (or,
        without `msg`, what `sender` did on `key`)."""
        self.rejected += 1
        if not self._journal_refusal(getattr(msg, "node", sender)):
            return
        self.commit(
            Rejection(
                run=self.run,
                reason=why,
                key=key[:1000],
                sender=getattr(msg, "node", sender),
                of="" if msg is None else msg.type,
                job=getattr(msg, "job", None),
            ),
            publish=False,
        )

    def _journal_refusal(self, sender: str | None) -> bool:
        """Whether a refusal of `sender`'s is journaled: the first `JOURNALED_REFUSALS` of its
        identity (`<id>.r<n>` is `<id>`) per `REFUSALS_S`, so that a flood of refused messages
        from one certificate grows the journal by a bounded amount a minute."""
        identity = incarnation(sender or "")[0]
        now = self.clock()
        start, count = self._refusals.get(identity, (now, 0))
        if now - start >= REFUSALS_S:
            start, count = now, 0
        if len(self._refusals) > 10_000:  # senders without a certificate may be any names
            self._refusals.clear()
        self._refusals[identity] = (start, count + 1)
        if count < JOURNALED_REFUSALS:
            return True
        self.unjournaled += 1
        return False

    def close(self) -> None:
        """Close the checkpoint files and the journal (the outbox is closed before)."""
        self.checkpoints.close()
        self.journal.close()
