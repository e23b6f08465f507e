"""The coordinator node: one loop for every coordinator, whose rules decide what messages mean.

The loop takes every subscription's messages from Zenoh's queues (`Inlet`), so the state has one
writer. It takes what is waiting as a group (group commit): whatever the group makes the
coordinator decide is committed through its `Ledger` (journaled, applied to the state, the
replies released by the outbox thread once the journal file is synced) while the loop goes on,
and only then published, so nothing is seen that a crash could forget. A worker that asks for
work (WorkerReady) gets the job its rules choose, or waits among the idle workers and gets one
as soon as there is some; one that asks again while it holds a job gets that job again. A worker
that loses its liveliness token, or sends no progress for its job's lease, loses the job (JobLost,
journaled): its agent goes to the next ready worker. Results go to the rules (`Rules`:
accept or reject), and so do failed jobs once checked and journaled; a message whose node differs
from its key's node segment is rejected by the bus check, journaled and counted. Once a second
the loop publishes the run's status, every 5 s its population; births and failed children go out
on ``births/<agent>``, and a Zenoh query on ``births/*`` or ``population`` answers a monitor that
starts late, one on ``checkpoint/<agent>`` a trainer whose child inherits that agent's weights.
When the state says the run is over, the rules write its results and the loop announces the
end a few times, then returns. While the journal or a checkpoint file cannot be
written (a full disk: `Ledger.stalled`) the loop commits nothing and publishes only what was on
the disk before, drops what would need a commit (the workers send their reports and asks
again), and tries every second to write again; then it goes on where it was, the jobs' leases
started afresh.
"""

from __future__ import annotations

import gc
import logging
import queue
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple, Protocol

import zenoh

from derl.messages import (
    Birth,
    ChildFailed,
    EvalResult,
    FitnessReport,
    InvalidKey,
    JobFailed,
    JobLost,
    KeySpace,
    MessageBase,
    RunStatus,
    TrainProgress,
    WorkerReady,
    encode,
    parse,
)
from derl.messages.dispatch import Handler, handles
from derl.messages.keys import REMEMBERED_BIRTHS
from derl.nodes.coordinator.ledger import Ledger
from derl.nodes.coordinator.rules import Rules
from derl.nodes.coordinator.run.audits import incarnation
from derl.nodes.runtime.bus import (
    INLET_CAPACITY,
    MSGPACK,
    Bus,
    Inlet,
    ZenohOptions,
    open_session,
)
from derl.nodes.runtime.rundir import lock_run_dir

log = logging.getLogger("derl.coordinator")

STATUS_PERIOD_S = 1.0
SNAPSHOT_PERIOD_S = 5.0
DONE_ANNOUNCEMENTS = 5
GROUP_S = 0.001  # a group's passes start within this of its first (measured at 1,000 simulated
# workers: 5 ms groups held replies back so long that the loop idled; 1 ms: +30%)
TAKE = 64  # messages a pass takes from one inlet before the next one's turn (8: -13% saturated)
RESEND_AFTER_S = 2.0  # a job order is sent again for a WorkerReady that came in this long after
# the last (`_ready`)
IDLE_S = (0.0005, 0.01)  # the wait when nothing came: the first, doubled up to the last
RETRY_S = 1.0  # a coordinator whose journal cannot be written tries again this often
REPORTS_HELD = 256  # reports an inlet holds (each up to 8 MiB: 2 GiB at most; ~100 kB usually)
INLETS = (  # what the loop takes, in this order in each pass, and how many each holds
    ("ready", (WorkerReady,), INLET_CAPACITY),
    ("fitness", (FitnessReport,), REPORTS_HELD),
    ("progress", (TrainProgress,), INLET_CAPACITY),
    ("eval", (EvalResult,), REPORTS_HELD),
    ("failure", (JobFailed,), INLET_CAPACITY),
)


class Publisher(Protocol):
    """Where the coordinator's replies go: the run's `Bus` once it serves, or what a tool or a
    test that drives it without a bus records them in (`Coordinator(..., publisher=)`)."""

    def publish(self, msg: MessageBase, data: bytes | None = None) -> None: ...


class Liveliness(NamedTuple):
    """A worker's liveliness token came (`up`) or went, as the loop takes it (`take`)."""

    role: str
    node: str
    up: bool


class Coordinator(Handler):
    """The node loop of run `run` in `run_dir`, with `rules` deciding what messages mean.

    `serve` runs it on the bus. A tool or a test drives it without one, in its own thread, as the
    loop does: `take` each message or liveliness change that came, `assign_idle`, then `settle`
    (the replies go to `publisher`). `clock` times all it does by the clock: leases, re-sent
    orders, groups, periodic messages, the ledger's windows (a test moves one by hand instead of
    sleeping)."""

    bus: Publisher
    """Where replies are published: the bus while it serves, else the `publisher` given."""

    def __init__(
        self,
        run: str,
        run_dir: Path,
        rules: Rules,
        publisher: Publisher | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if publisher is not None:
            self.bus = publisher
        self.run, self.rules, self.clock = run, rules, clock
        self.state = rules.state
        self.ledger = Ledger(run, run_dir, rules.state, clock)
        rules.start(self.ledger)
        self.keys = KeySpace(run)
        self.recent: deque[tuple[str, bytes]] = deque(maxlen=REMEMBERED_BIRTHS)  # (key, payload)
        self.recent_lock = threading.Lock()
        for birth in self.state.births[-REMEMBERED_BIRTHS:]:
            self._remember(birth, encode(birth))
        now = self.clock()
        self.heard = {job: now for job in self.state.jobs}  # leases restart on a restart
        self.ordered: dict[str, float] = {}  # node -> when its job's order last went out
        self.ready_inlet: Inlet | None = None  # where WorkerReady comes in (None: handlers
        # called directly, each message just arrived)
        self.alive: dict[str, str] = {}  # node -> role
        self.tokens: set[str] = set()  # nodes whose liveliness token is up
        self.incarnations: dict[str, str] = {}  # identity -> its one live node (`incarnation`)
        self.refused: set[str] = set()  # nodes refused as another incarnation of a live one
        # role -> the workers that asked and got no work, first asked first (`assign_idle`)
        self.idle: dict[str, dict[str, None]] = {"trainer": {}, "evaluator": {}}
        self.trainers = 0  # of them, trainers (counted, not scanned: one count per assignment)
        self.rates: dict[str, float] = {}  # node -> steps/s
        self.failures_held: list[JobFailed] = []  # JobFailed that came while stalled
        self.retry_at = 0.0  # when a stalled coordinator next tries to write its journal
        self.stop = threading.Event()
        log.info("run %s: %d journaled messages replayed, %d born", run, self.ledger.replayed,
                 rules.progress().born)  # fmt: skip

    # --- the loop ----------------------------------------------------------------------------

    def serve(self, options: ZenohOptions) -> bool:
        """Run until the run is finished (True) or `stop` is set (False)."""
        with open_session(options) as session:
            self.bus = bus = Bus(session, self.run, on_reject=self._bus_rejected)
            inlets = [
                bus.inlet(bus.keys.all(kind), types, held, clock=self.clock)
                for kind, types, held in INLETS
            ]
            self.ready_inlet = inlets[0]
            changes: queue.SimpleQueue[tuple[str, str, bool]] = queue.SimpleQueue()
            bus.watch_alive(lambda role, node, up: changes.put(Liveliness(role, node, up)))
            queryables = [
                session.declare_queryable(bus.keys.all("births"), self._answer_births),
                session.declare_queryable(bus.keys.population(), self._answer_population),
                session.declare_queryable(bus.keys.all("checkpoint"), self._answer_checkpoint),
            ]
            finished = self._loop(inlets, changes)
            for queryable in queryables:
                queryable.undeclare()
            self.close()
        return finished

    def _loop(self, inlets: list[Inlet], changes: queue.SimpleQueue) -> bool:
        """Take a group, hand out work, commit, publish what is released; once a second the
        status, every 5 s the population. Until the end is announced (True) or `stop` is set."""
        next_second = next_snapshot = 0.0
        announced = 0
        idle_s = IDLE_S[0]
        outbox = self.ledger.outbox
        while not self.stop.is_set():
            if self.ledger.stalled:
                self._stalled(inlets)
                continue
            took = self._take_group(inlets, changes)
            self.ledger.flush()  # the group's births and Acks do not wait for the breeding below
            self.assign_idle()
            self.ledger.flush()
            outbox.released.clear()
            if self._publish_released() or took:
                idle_s = IDLE_S[0]
            else:  # until replies are released or the wait is over
                outbox.released.wait(idle_s)
                idle_s = min(2 * idle_s, IDLE_S[1])
            now = self.clock()
            if now >= next_second:
                next_second = now + STATUS_PERIOD_S
                if self._every_second(now, last_end=announced == DONE_ANNOUNCEMENTS - 1):
                    announced += 1
                    if announced >= DONE_ANNOUNCEMENTS:
                        return True
            if now >= next_snapshot:
                self._say(self.rules.snapshot())
                next_snapshot = now + SNAPSHOT_PERIOD_S
        return False

    def _stalled(self, inlets: list[Inlet]) -> None:
        """The journal or a checkpoint cannot be written: take what comes without committing
        anything (progress keeps its job's lease; a failed job waits for later; reports and asks
        are dropped: their senders send them again; liveliness changes wait in their queue), and
        every `RETRY_S` try to write again. Once it works, the leases start afresh."""
        for inlet in inlets:
            for msg in inlet.take(TAKE):
                if isinstance(msg, TrainProgress):  # the one kind taken while stalled
                    self.dispatch(msg)
                elif isinstance(msg, JobFailed):
                    self.failures_held.append(msg)
        self._publish_released()  # what was on the disk before goes out
        now = self.clock()
        if now < self.retry_at:
            self.stop.wait(0.05)
            return
        self.retry_at = now + RETRY_S
        if self.ledger.recover():
            self.heard.update(dict.fromkeys(self.state.jobs, now))
            held, self.failures_held = self.failures_held, []
            for failure in held:
                self.take(failure)

    def _every_second(self, now: float, last_end: bool) -> bool:
        """Log, check the leases, say the status; whether the run is over (the `last_end` time,
        its results are written once what it said is on disk: not the first, since a child born
        just before a crash gets its checkpoint from a report its trainer sends again)."""
        # The state only grows (every body, every job) and its handling makes no cyclic garbage,
        # so once a second everything alive leaves the cyclic GC's care: else its full passes over
        # a large run's state stall the loop for hundreds of ms (measured: 0.5 s at 20k births).
        gc.freeze()
        self.rules.log_progress()
        self._check_leases(now)
        self._say(self.status())
        if not self.state.finished:
            return False
        if last_end:
            self.ledger.drain()  # the best agents' checkpoints are on disk
            if self.ledger.stalled:  # not yet: the end waits until the files are written
                return False
            self._publish_released()
            self.rules.finish()
        return True

    def close(self) -> None:
        """Publish what is waiting, then close the checkpoint files and the journal."""
        self.ledger.flush()
        self.ledger.outbox.close()
        self._publish_released()
        self.ledger.close()

    def _take_group(self, inlets: list[Inlet], changes: queue.SimpleQueue) -> bool:
        """Handle what is waiting (liveliness changes, then each inlet's messages in turn) in
        passes, a new one only within `GROUP_S`; whether there was anything."""
        took = False
        until = self.clock() + GROUP_S
        while True:
            taken: list[MessageBase | tuple[str, str, bool]] = []
            while not changes.empty():
                taken.append(changes.get())
            for inlet in inlets:
                taken += inlet.take(TAKE)
            for item in taken:
                self.take(item)
            took = took or bool(taken)
            if not taken or self.clock() >= until:
                return took

    def take(self, item: MessageBase | tuple[str, str, bool]) -> None:
        """Handle one thing that came: a message (`dispatch`) or a liveliness change
        (`Liveliness`). What it fails on is logged and counted as rejected, never raised: one
        message must never stop the run."""
        try:
            if isinstance(item, tuple):
                self._liveliness(*item)
            else:
                self.dispatch(item)
        except Exception:  # one message must never stop the run: log it and go on
            self.ledger.rejected += 1
            what = (
                item
                if not isinstance(item, MessageBase)
                else (f"{item.type} {getattr(item, 'job', '')} from {getattr(item, 'node', '?')}")
            )
            log.exception("handling %s failed", what)

    # --- what the workers send (`dispatch`) ---------------------------------------------------

    @handles(TrainProgress)
    def _progress(self, msg: TrainProgress) -> None:
        job = self.state.jobs.get(msg.job)
        if job is not None and job.node == msg.node:
            self.heard[msg.job] = self.clock()
            self.rates[msg.node] = msg.steps_per_s

    @handles(FitnessReport)
    def _fitness(self, msg: FitnessReport) -> None:
        self.rules.on_fitness(msg)

    @handles(EvalResult)
    def _evaluation(self, msg: EvalResult) -> None:
        self.rules.on_evaluation(msg)

    def settle(self) -> None:
        """Flush the group, wait until it is on the disk and publish its replies (the loop does
        this without waiting; tests and tools that drive the handlers call this)."""
        self.ledger.flush()
        self.ledger.drain()
        self._publish_released()

    def _publish_released(self) -> int:
        """Publish the replies the outbox released; how many."""
        replies = self.ledger.outbox.take()
        for msg, data in replies:
            try:
                self.bus.publish(msg, data=data)
            except Exception:  # one reply must never stop the others
                log.exception("publishing %s failed", msg)
            if isinstance(msg, Birth | ChildFailed):
                self._remember(msg, data)
        return len(replies)

    def _say(self, msg: MessageBase) -> None:
        """Publish a message that is not journaled (status, snapshot) in order after the
        group before it."""
        self.ledger.send(msg)
        self.ledger.flush()

    # --- assignments -------------------------------------------------------------------------

    @handles(WorkerReady)
    def _ready(self, ready: WorkerReady) -> None:
        if ready.node not in self.tokens:  # no work without a liveliness token (it asks again)
            log.debug("%s asked for work before its liveliness token came", ready.node)
            return
        if ready.node not in self.alive and not self._join(ready.node, ready.role):
            return
        current = self.state.job_of(ready.node)
        if current is not None:  # it missed its job (e.g. the coordinator restarted) ...
            # ... or asked before the job reached it: sent again only if the ask came in at
            # least RESEND_AFTER_S after the job went out. Under a backlog an ask waits in the
            # inlet for seconds, so when it is handled says nothing; it came in after the inlet
            # was last seen empty (at 10,000 workers, counting from when it was handled sent
            # five copies per assignment of jobs that had reached their workers long before)
            last, now = self.ordered.get(ready.node), self.clock()
            came = now if self.ready_inlet is None else self.ready_inlet.arrived_after
            if last is None or came - last >= RESEND_AFTER_S:
                self.ordered[ready.node] = now
                self.ledger.send(current.order)
            return
        self._assign(ready.node, ready.role)

    def _assign(self, node: str, role: str) -> bool:
        """The next job of `role` for `node`, if there is one (whether it got one); else it
        waits among the idle workers (keeping its place if it waited already). A worker that
        refused the run's jobs (`JobFailed.unfit`) gets none."""
        if node in self.state.unfit:
            return False
        job = self.rules.next_job(node, role, self.trainers)
        if job is None:
            if incarnation(node)[0] not in self.state.quarantined:  # those never get work
                self.idle[role][node] = None
            return False
        self.ledger.commit(job)
        self.heard[job.job] = self.ordered[node] = self.clock()
        self.idle[role].pop(node, None)
        return True

    def assign_idle(self) -> None:
        """Work for the workers that asked and got none, as soon as there is some (a birth, a
        job taken back), first asked first: they need not ask again for it. At most `GROUP_S`
        of it per turn of the loop: thousands of workers idle until the initial bodies are born
        would otherwise hold the loop for seconds."""
        until = self.clock() + GROUP_S
        for role, waiting in self.idle.items():
            for node in list(waiting):
                if self.clock() >= until:
                    return
                if not self._assign(node, role) and not self.state.queued(role):
                    break  # no work for this role now

    # --- failures, rejections ----------------------------------------------------------------

    @handles(JobFailed)
    def _job_failed(self, failure: JobFailed) -> None:
        job = self.state.jobs.get(failure.job)
        if job is None or job.node != failure.node or job.agent != failure.agent:
            self.ledger.rejection("failure of a job not held by its sender", "", failure)
            return
        if failure.unfit:  # once: it gets no more jobs
            log.warning("%s refused %s and gets no more of this run's jobs: %s", failure.node,
                        failure.job, failure.error)  # fmt: skip
            self.ledger.commit(failure, publish=False)
            self.idle["trainer"].pop(failure.node, None)
            self.idle["evaluator"].pop(failure.node, None)
            return
        log.warning("%s failed on %s: %s", failure.agent, failure.node, failure.error)
        self.ledger.commit(failure, publish=False)
        self.rules.on_failure(failure, job)

    def _bus_rejected(self, why: str, key: str, msg: MessageBase | None) -> None:
        """A message the bus check refused; the ones that decode are journaled (`Rejection`)."""
        if msg is None or msg.run != self.run or self.ledger.stalled:
            self.ledger.rejected += 1  # garbage, another run's, or while nothing can be
            return  # journaled: counted (the bus logged it)
        self.ledger.rejection(why, key, msg)

    # --- workers and leases ------------------------------------------------------------------

    def _join(self, node: str, role: str) -> bool:
        """`node` is alive (whether it may work): one live node per identity (`incarnation`), a
        later restart's ending the earlier one's job; an earlier or equal one is refused."""
        identity, number = incarnation(node)
        current = self.incarnations.get(identity)
        if current is not None and current != node:
            if number <= incarnation(current)[1]:
                if node not in self.refused:  # journaled once: it may ask every second
                    self.refused.add(node)
                    why = f"{current} is alive: one worker per identity"
                    self.ledger.rejection(why, self.keys.alive(role, node), sender=node)
                return False
            self._lost(current, f"{node} came after it")
        self._leave(node)
        self.alive[node] = role
        self.trainers += role == "trainer"
        self.incarnations[identity] = node
        return True

    def _leave(self, node: str) -> None:
        role = self.alive.pop(node, None)
        self.trainers -= role == "trainer"
        if role is not None:
            self.idle[role].pop(node, None)
            identity = incarnation(node)[0]
            if self.incarnations.get(identity) == node:
                del self.incarnations[identity]

    def _liveliness(self, role: str, node: str, up: bool) -> None:
        if up:
            self.tokens.add(node)
            self._join(node, role)
            return
        self.tokens.discard(node)
        self._lost(node, "node left")

    def _lost(self, node: str, reason: str) -> None:
        """`node` is gone: its job, if any, goes back to the queue."""
        self._leave(node)
        self.rates.pop(node, None)
        job = self.state.job_of(node)
        if job is not None:
            log.warning("%s: %s; %s goes back to the queue", node, reason, job.agent)
            self.ledger.commit(JobLost(run=self.run, job=job.id, node=node, reason=reason))

    def _check_leases(self, now: float) -> None:
        for job in list(self.state.jobs.values()):
            lease_s = job.order.lease_s
            if now - self.heard.get(job.id, now) > lease_s:
                reason = f"no progress for {lease_s:g} s"
                log.warning("%s: %s; %s goes back to the queue", job.node, reason, job.agent)
                self.ledger.commit(JobLost(run=self.run, job=job.id, node=job.node, reason=reason))

    # --- what the run looks like -------------------------------------------------------------

    def _remember(self, msg: Birth | ChildFailed, data: bytes) -> None:
        with self.recent_lock:
            self.recent.append((self.keys.key_for(msg), data))

    def _answer_births(self, query: zenoh.Query) -> None:
        """A monitor's query on ``births/*``: the latest births and failed children, oldest
        first."""
        with self.recent_lock:
            recent = list(self.recent)
        for key, data in recent:
            query.reply(key, data, encoding=MSGPACK)

    def _answer_checkpoint(self, query: zenoh.Query) -> None:
        """A trainer's query on ``checkpoint/<agent>`` (a child that inherits its parent's
        weights): the agent's checkpoint file, once it is on the disk; before, no answer (the
        trainer asks again: the file is written beside the loop)."""
        try:
            agent = parse(str(query.key_expr)).parts[0]
            data = self.ledger.checkpoints.path(agent).read_bytes()
        except (InvalidKey, OSError):
            return
        query.reply(self.keys.checkpoint(agent), data)

    def _answer_population(self, query: zenoh.Query) -> None:
        snapshot = encode(self.rules.snapshot())
        query.reply(self.keys.population(), snapshot, encoding=MSGPACK)

    def status(self) -> RunStatus:
        """The run now, as the loop publishes it every second."""
        progress, state = self.rules.progress(), self.state
        return RunStatus(
            run=self.run,
            born=progress.born,
            target=progress.target,
            best_fitness=progress.best_fitness,
            best_agent=progress.best_agent,
            in_flight=len(state.jobs),
            workers_alive=len(self.alive),
            evaluated=state.evaluated,
            eval_target=state.eval_target,
            failed=len(state.failed),
            repeats=state.repeats,
            audited=progress.audited,
            quarantined=tuple(state.quarantined),
            retraining=progress.retraining,
            rejected=self.ledger.rejected,
            steps_per_s=sum(self.rates.values()),
            done=state.finished,
        )


def serve(run: str, run_dir: Path, rules: Callable[[], Rules], options: ZenohOptions) -> bool:
    """The coordinator of `run` in `run_dir`, with the rules `rules()` makes, until the run is
    finished (True) or it is stopped (False); the run directory is locked from before the rules
    read its files until the end (`RunDirLocked` if another process holds it)."""
    with lock_run_dir(run_dir):
        coordinator = Coordinator(run, run_dir, rules())
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: coordinator.stop.set())
        return coordinator.serve(options)
