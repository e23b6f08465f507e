"""The coordinator node: owns the population, hands out jobs, journals everything it decides.

It runs one loop that takes every subscription's messages from Zenoh's queues (`Inlet`), so the
state has one writer. Every message it accepts or sends is first appended to the run's MCAP
journal and applied to `CoordinatorState` (the same handlers that rebuild the state on restart),
then published. It takes what is waiting as a group (group commit): the group's messages are
journaled and written into the journal file, the outbox thread fsyncs the file once for every
group waiting (`Outbox`) while the loop goes on, and only then is what they made the coordinator
say published, so nothing is seen that a crash could forget. A worker that loses its liveliness
token, or sends no progress for its job's lease, loses the job (JobLost, journaled); the child
goes to the next ready worker, and the first valid report for a child wins, whoever trained it
(the other job is cancelled). A report is acknowledged once its checkpoint is on disk, and
answered with a Reject when it can never be accepted (a job never issued to the sender, another
body than its job's, an impossible fitness); a message whose node differs from its key's node
segment is rejected by the bus check. Each of these is journaled and counted. A failed job
(JobFailed) is retried on another worker up to `max_attempts` times, then the child is given up
(ChildFailed). Before a tournament child is assigned the coordinator looks its body up
(`Evolution.repeat`: its first draft, ~0.1 ms, and breeding only if that is a born body): a body
born already is not trained again, the child is born at once as its repeat (Birth `repeat_of`,
with its result, and its checkpoint file linked) and the worker gets the next child. A child
whose first draft is that of a child in training is held back until that one is born
(`CoordinatorState.hold`), then looked up again: it is then most likely its repeat. Births and
failed children go out on ``births/<child>``; a Zenoh query on ``births/*`` or
``population`` answers a monitor that starts late.
"""

from __future__ import annotations

import gc
import json
import logging
import math
import queue
import signal
import threading
import time
from collections import deque
from concurrent.futures import Future
from pathlib import Path

import zenoh
from derl.messages import (
    Ack,
    Birth,
    Cancel,
    ChildFailed,
    EvalJob,
    EvalResult,
    FitnessReport,
    JobFailed,
    JobLost,
    KeySpace,
    Member,
    MessageBase,
    PopulationSnapshot,
    Reject,
    Rejection,
    RunStatus,
    TrainJob,
    TrainProgress,
    WorkerReady,
    encode,
)
from derl.messages.examples import GENOME
from derl.nodes.coordinator.outbox import Outbox, Reply
from derl.nodes.coordinator.state import CoordinatorState, tournament_message
from derl.nodes.journal.segments import Journal, JournalDamaged, replay, segments
from derl.nodes.runtime.bus import MSGPACK, Bus, Inlet, ZenohOptions, open_session
from derl.nodes.runtime.checkpoints import CheckpointFiles
from derl.nodes.runtime.rundir import RunDirLocked, lock_run_dir, write_atomic
from pydantic import ValidationError

from derl.evolution import EvolutionConfig
from derl.rl.config import SAVED
from derl.unimal import Genome, to_mjcf
from derl.validation import problems

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
RECENT_BIRTHS = 1000  # births a late monitor gets by query
PROFILE_FILE = "profile.json"
INITIAL_FILE = "initial_population.json"


class Coordinator:
    def __init__(self, run: str, run_dir: Path, config: EvolutionConfig) -> None:
        self.run, self.run_dir = run, run_dir
        run_dir.mkdir(parents=True, exist_ok=True)
        self.config = self._run_config(config)
        self.state = self._new_state()
        replayed = 0
        if segments(run_dir):
            try:
                for msg in replay(run_dir):
                    if self.state.known(msg):  # what it decides live is known
                        self.state.apply(msg)
                        replayed += 1
            except JournalDamaged as damage:
                raise SystemExit(f"derl: {damage}") from None
        if self.state.run not in (None, run):  # its own messages would not change the state
            raise SystemExit(f"derl: {run_dir} holds the journal of run {self.state.run!r}, not "
                             f"{run!r}: resume it with --run {self.state.run}")  # fmt: skip
        self.replayed = replayed
        self.journal = Journal(run_dir)
        self.checkpoints = CheckpointFiles(run_dir)
        self._resume()
        # the group's replies: published once it is on disk (an Ack, once its checkpoint is)
        self.outbox: list[Reply] = []
        self.sender = Outbox(self.journal.sync)
        self.keys = KeySpace(run)
        self.recent: deque[tuple[str, bytes]] = deque(maxlen=RECENT_BIRTHS)  # (key, payload)
        self.recent_lock = threading.Lock()
        for birth in self.state.births[-RECENT_BIRTHS:]:
            self._remember(birth, encode(birth))
        now = time.monotonic()
        self.heard = {job: now for job in self.state.jobs}  # leases restart on a restart
        self.ordered: dict[str, float] = {}  # node -> when its job's order last went out
        self.ready_inlet: Inlet | None = None  # where WorkerReady comes in (None: handlers
        # called directly, each message just arrived)
        self.alive: dict[str, str] = {}  # node -> role
        # role -> the workers that asked and got no work, first asked first (`_assign_idle`)
        self.idle: dict[str, dict[str, None]] = {"trainer": {}, "evaluator": {}}
        self.trainers = 0  # of them, trainers (counted, not scanned: one count per assignment)
        self.rates: dict[str, float] = {}  # node -> steps/s
        self.rejected = 0
        self.stop = threading.Event()
        log.info("run %s: %d journaled messages replayed, %d born", run, replayed, self.born)

    def _new_state(self) -> CoordinatorState:
        """The state before the journal is replayed: the initial population to be trained."""
        check_jobs(self.run, self.config)
        state = CoordinatorState.start(self.config, self._saved_initial_population())
        self._save_initial_population(state)
        return state

    def _resume(self) -> None:
        """What the journal's replay leaves to redo: holds behind children in training, and the
        checkpoint links of repeats a crash may have lost."""
        self.logged_born = self.born
        for child in self.state.by_child:  # children in training hold later equal ones
            self.state.training(child)
        for birth in self.state.births:
            if birth.repeat_of is not None and not self.checkpoints.path(birth.child).exists():
                self.checkpoints.link(birth.child, birth.repeat_of).add_done_callback(
                    _log_failed_link
                )
        # the same for every job of the run: built once (each builds the world's task)
        self.training_ppo = self.config.training_ppo()
        self.fitness_bound = self.config.fitness_bound()

    @property
    def born(self) -> int:
        return len(self.state.evolution.born)

    # --- setup -------------------------------------------------------------------------------

    def _run_config(self, given: EvolutionConfig) -> EvolutionConfig:
        """The run's configuration: the one saved with it when it resumes (the code's defaults
        may have changed since), else `given`, saved now."""
        path = self.run_dir / PROFILE_FILE
        if not path.exists():
            write_atomic(path, given.model_dump_json(indent=2) + "\n")
            return given
        try:
            saved = EvolutionConfig.model_validate_json(path.read_text(), context=SAVED)
        except ValidationError as error:
            raise SystemExit(
                f"derl: {path} is not a valid run configuration: {problems(error)}"
            ) from None
        if (saved.name, saved.world, saved.seed) != (given.name, given.world, given.seed):
            raise SystemExit(
                f"derl: {self.run_dir} holds a run of profile {saved.name} in {saved.world} with "
                f"seed {saved.seed}, not {given.name} in {given.world} with seed {given.seed}; "
                "resume it with the same profile and seed or use a new --run-dir"
            )
        if saved != given:
            changed = sorted(k for k in type(given).model_fields if getattr(saved, k) !=
                             getattr(given, k))  # fmt: skip
            log.warning("resuming with the run's saved settings (%s differ from the profile's "
                        "today)", ", ".join(changed))  # fmt: skip
        return saved

    def _saved_initial_population(self) -> list[Genome] | None:
        """The initial bodies, if this run drew them before (else `Evolution` draws them)."""
        path = self.run_dir / INITIAL_FILE
        if not path.exists():
            return None
        return [Genome.model_validate(g) for g in json.loads(path.read_text())]

    def _save_initial_population(self, state: CoordinatorState) -> None:
        """Keep the initial bodies as a fact of the run (drawing them again is slow)."""
        path = self.run_dir / INITIAL_FILE
        if not path.exists():
            bodies = [c.genome.model_dump() for c in state.evolution.initial]
            write_atomic(path, json.dumps(bodies))

    # --- the loop ----------------------------------------------------------------------------

    def serve(self, options: ZenohOptions) -> bool:
        """Run until the run is finished (True) or `stop` is set (False)."""
        finished = False
        with open_session(options) as session:
            bus = Bus(session, self.run, on_reject=self._bus_rejected)
            inlets = [
                bus.inlet(bus.keys.all(kind), types)
                for kind, types in (
                    ("ready", (WorkerReady,)),
                    ("fitness", (FitnessReport,)),
                    ("progress", (TrainProgress,)),
                    ("eval", (EvalResult,)),
                    ("failure", (JobFailed,)),
                )
            ]
            self.ready_inlet = inlets[0]
            changes: queue.SimpleQueue[tuple[str, str, bool]] = queue.SimpleQueue()
            bus.watch_alive(lambda role, node, up: changes.put((role, node, up)))
            queryables = [
                session.declare_queryable(bus.keys.all("births"), self._answer_births),
                session.declare_queryable(bus.keys.population(), self._answer_population),
            ]
            self.bus = bus
            next_status = next_snapshot = 0.0
            announced = 0
            idle_s = IDLE_S[0]
            while not self.stop.is_set():
                took = self._take_group(inlets, changes)
                self._assign_idle()
                self._flush()
                self.sender.released.clear()
                if self._publish_released() or took:
                    idle_s = IDLE_S[0]
                else:  # until replies are released or the wait is over
                    self.sender.released.wait(idle_s)
                    idle_s = min(2 * idle_s, IDLE_S[1])
                now = time.monotonic()
                if now >= next_status:
                    # The state only grows (every body, every job) and its handling makes no
                    # cyclic garbage, so once a second everything alive leaves the cyclic GC's
                    # care: else its full passes over a large run's state stall the loop for
                    # hundreds of ms (measured: 0.5 s at 20k births).
                    gc.freeze()
                    self._log_births()
                    self._check_leases(now)
                    self._say(self._status())
                    next_status = now + STATUS_PERIOD_S
                    if self.state.finished:
                        announced += 1
                        if announced == DONE_ANNOUNCEMENTS:  # not the first: a child born
                            # just before a crash gets its checkpoint from a re-sent report
                            self.sender.drain()  # the best agents' checkpoints are on disk
                            self._publish_released()
                            self._write_results()
                        if announced >= DONE_ANNOUNCEMENTS:
                            finished = True
                            break
                if now >= next_snapshot:
                    self._say(self._snapshot())
                    next_snapshot = now + SNAPSHOT_PERIOD_S
            for queryable in queryables:
                queryable.undeclare()
            self.close()
        return finished

    def close(self) -> None:
        """Publish what is waiting, then close the checkpoint files and the journal."""
        self._flush()
        self.sender.close()
        self._publish_released()
        self.checkpoints.close()
        self.journal.close()

    def _take_group(self, inlets: list[Inlet], changes: queue.SimpleQueue) -> bool:
        """Handle what is waiting (liveliness changes, then each inlet's messages in turn) in
        passes, a new one only within `GROUP_S`; whether there was anything."""
        took = False
        until = time.monotonic() + GROUP_S
        while True:
            taken: list[object] = []
            while not changes.empty():
                taken.append(changes.get())
            for inlet in inlets:
                taken += inlet.take(TAKE)
            for item in taken:
                self._take(item)
            took = took or bool(taken)
            if not taken or time.monotonic() >= until:
                return took

    def _take(self, item: object) -> None:
        try:
            if isinstance(item, tuple):
                self._liveliness(*item)
            else:
                self._handle(item)
        except Exception:  # one message must never stop the run: log it and go on
            self.rejected += 1
            log.exception("handling %r failed", item)

    def _commit(
        self, msg: MessageBase, publish: bool = True, after: Future[None] | None = None
    ) -> None:
        """Journal and apply; what the coordinator says is published by the next `_flush`
        (once `after` is done, and not if it failed)."""
        data = encode(msg)
        self.journal.write(msg, data=data, flush=False)
        self.state.apply(msg)
        if publish:
            self.outbox.append((msg, data, after))

    def _flush(self) -> None:
        """The group's messages into the journal file; its replies are released once the file
        is on the disk (`Outbox`)."""
        if not self.outbox and not self.journal.pending:
            return
        self.journal.flush()
        self.sender.send(self.outbox)
        self.outbox = []

    def settle(self) -> None:
        """Flush the group, wait until it is on the disk and publish its replies (the loop does
        this without waiting; tests and tools that drive the handlers call this)."""
        self._flush()
        self.sender.drain()
        self._publish_released()

    def _publish_released(self) -> int:
        """Publish the replies the outbox released; how many."""
        replies = self.sender.take()
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
        self.outbox.append((msg, encode(msg), None))
        self._flush()

    def _handle(self, msg: object) -> None:
        if isinstance(msg, WorkerReady):
            self._ready(msg)
        elif isinstance(msg, TrainProgress):
            job = self.state.jobs.get(msg.job)
            if job is not None and job.node == msg.node:
                self.heard[msg.job] = time.monotonic()
                self.rates[msg.node] = msg.steps_per_s
        elif isinstance(msg, FitnessReport):
            self._fitness(msg)
        elif isinstance(msg, EvalResult):
            self._evaluation(msg)
        elif isinstance(msg, JobFailed):
            self._job_failed(msg)

    # --- assignments -------------------------------------------------------------------------

    def _ready(self, ready: WorkerReady) -> None:
        if ready.node not in self.alive:
            self._join(ready.node, ready.role)
        current = self.state.job_of(ready.node)
        if current is not None:  # it missed its job (e.g. the coordinator restarted) ...
            # ... or asked before the job reached it: sent again only if the ask came in at
            # least RESEND_AFTER_S after the job went out. Under a backlog an ask waits in the
            # inlet for seconds, so when it is handled says nothing; it came in after the inlet
            # was last seen empty (at 10,000 workers, counting from when it was handled sent
            # five copies per assignment of jobs that had reached their workers long before)
            last, now = self.ordered.get(ready.node), time.monotonic()
            came = now if self.ready_inlet is None else self.ready_inlet.arrived_after
            if last is None or came - last >= RESEND_AFTER_S:
                self.ordered[ready.node] = now
                self.outbox.append((current.order, encode(current.order), None))
            return
        self._assign(ready.node, ready.role)

    def _assign(self, node: str, role: str) -> bool:
        """The next job of `role` for `node`, if there is one (whether it got one); else it
        waits among the idle workers (keeping its place if it waited already)."""
        if role == "trainer":
            self._assign_training(node)
        else:
            self._assign_evaluation(node)
        if self.state.job_of(node) is None:
            self.idle[role][node] = None
            return False
        self.idle[role].pop(node, None)
        return True

    def _assign_idle(self) -> None:
        """Work for the workers that asked and got none, as soon as there is some (a birth, a
        job taken back), first asked first: they need not ask again for it. At most `GROUP_S`
        of it per turn of the loop: thousands of workers idle until the initial bodies are born
        would otherwise hold the loop for seconds."""
        until = time.monotonic() + GROUP_S
        for role, waiting in self.idle.items():
            while waiting and time.monotonic() < until:
                if not self._assign(next(iter(waiting)), role):
                    break  # no work for this role now

    def _assign_training(self, node: str) -> None:
        """The next child to train for `node`; children whose body is born already are born as
        repeats on the way, without training."""
        state, evolution = self.state, self.state.evolution
        while True:
            child = state.next_child_for(node, self.trainers)
            if child is None and not state.waiting and state.wants_tournament():
                decided = evolution.tournament()
                self._commit(tournament_message(self.run, decided))
                child = decided.name
            if child is None:
                return
            if not self._born_as_repeat(child) and not state.hold(child):
                break
        state.training(child)
        genome, mutation_seed = evolution.to_train(child)
        job = TrainJob(
            run=self.run,
            job=state.next_job_id(child),
            child=child,
            node=node,
            genome=genome,
            task=self.config.world,
            ppo=self.training_ppo,
            parent=evolution.parents[child],
            mutation_seed=mutation_seed,
            lease_s=self.config.lease_s,
        )
        self._commit(job)
        self.heard[job.job] = self.ordered[node] = time.monotonic()
        log.debug("%s -> %s (%s)", child, node, job.job)

    def _born_as_repeat(self, child: str) -> bool:
        """If `child`'s body is born already (a repeat: training is deterministic within a
        run), it is born now with that body's result and checkpoint, and True."""
        state = self.state
        repeat = state.evolution.repeat(child)
        if repeat is None:
            return False
        earlier, genome, mutation = repeat
        first = state.born[earlier]
        parent = state.evolution.parents[child]
        birth = first.model_copy(
            update={
                "child": child,
                "parent": parent,
                "birth": len(state.births),
                "generation": state.generation(parent),
                "mutation": mutation.op,
                "mutation_detail": mutation.detail,
                "genome": genome,
                "repeat_of": earlier,
            }
        )
        self.checkpoints.link(child, earlier).add_done_callback(_log_failed_link)
        self._commit(birth)
        log.debug("born %s as a repeat of %s", child, earlier)
        return True

    def _assign_evaluation(self, node: str) -> None:
        key = self.state.next_evaluation()
        if key is None:
            return
        agent, task, _, _ = key
        genome, ppo = self.state.evaluation_order(key)
        job = EvalJob(
            run=self.run,
            job=f"e{len(self.state.issued) + 1}-{agent}"[:128],
            agent=agent,
            node=node,
            genome=genome,
            task=task,
            ppo=ppo,
            lease_s=self.config.lease_s,
        )
        self._commit(job)
        self.heard[job.job] = self.ordered[node] = time.monotonic()

    # --- results -----------------------------------------------------------------------------

    def _ack(
        self, msg: FitnessReport | EvalResult, subject: str, after: Future[None] | None = None
    ) -> None:
        ack = Ack(run=self.run, of=msg.type, job=msg.job, child=subject, node=msg.node)
        self._commit(ack, after=after)

    def _reject(self, msg: FitnessReport | EvalResult, subject: str, reason: str) -> None:
        """Refuse a result for good: journaled, counted, and the sender told to drop it."""
        self.rejected += 1
        what = "fitness" if isinstance(msg, FitnessReport) else "evaluation"
        log.warning("rejected %s of %s from %s: %s", what, subject, msg.node, reason)
        reject = Reject(
            run=self.run, of=msg.type, job=msg.job, child=subject, node=msg.node, reason=reason
        )
        self._commit(reject)

    def _bus_rejected(self, why: str, key: str, msg: MessageBase | None) -> None:
        """A message the bus check refused; the ones that decode are journaled (`Rejection`)."""
        if msg is None or msg.run != self.run:
            self.rejected += 1  # garbage or another run's: counted (the bus logged it)
            return
        self._rejection(why, key, msg)

    def _rejection(self, why: str, key: str, msg: MessageBase) -> None:
        self.rejected += 1
        self._commit(
            Rejection(
                run=self.run,
                reason=why,
                key=key[:1000],
                sender=getattr(msg, "node", None),
                of=msg.type,
                job=getattr(msg, "job", None),
            ),
            publish=False,
        )

    def _fitness(self, report: FitnessReport) -> None:
        state = self.state
        order = state.orders.get(report.job)
        if report.child in state.born:
            log.info("%s already born: repeated report acknowledged", report.child)
            saved = None  # a crash (or a failed write) may have lost its checkpoint file
            born_from = state.born[report.child].job
            if born_from == report.job and not self.checkpoints.path(report.child).exists():
                saved = self.checkpoints.save(report.child, report.checkpoint)
            self._ack(report, report.child, after=saved)
        elif report.child in state.failed:
            self._reject(report, report.child, "the child was given up")
        elif (
            order is None
            or not isinstance(order, TrainJob)
            or order.node != report.node
            or order.child != report.child
        ):
            self._reject(report, report.child, f"job {report.job} was never issued to "
                         f"{report.node} for {report.child}")  # fmt: skip
        elif wrong := self._wrong_report(report, order):
            self._reject(report, report.child, wrong)
        else:
            self._birth(report, order)

    def _birth(self, report: FitnessReport, order: TrainJob) -> None:
        """The first valid report for a child: its birth (and the end of any other job for it)."""
        state = self.state
        saved = self.checkpoints.save(report.child, report.checkpoint)
        self._commit(report.model_copy(update={"checkpoint": b""}), publish=False)
        birth = Birth(
            run=self.run,
            child=report.child,
            parent=order.parent,
            job=report.job,
            node=report.node,
            birth=len(state.births),
            generation=state.generation(order.parent),
            fitness=report.fitness,
            cost_of_work=report.cost_of_work,
            energy=report.energy,
            mass=report.mass,
            mutation=report.mutation,
            mutation_detail=report.mutation_detail,
            genome=report.genome,
        )
        other = state.by_child.get(report.child)
        self._commit(birth)
        log.debug("born %s fitness %.2f", report.child, report.fitness)
        self._ack(report, report.child, after=saved)
        if other is not None and other != report.job:
            node = state.jobs[other].node
            self._commit(Cancel(run=self.run, job=other, node=node,
                                reason=f"{report.child} was born from {report.job}"))  # fmt: skip

    def _wrong_report(self, report: FitnessReport, order: TrainJob) -> str:
        """Why `report` cannot be accepted for `order` ("" if it can).

        A child bred by its trainer is taken as reported (breeding is deterministic and trainers
        are trusted like their fitness; with TLS only the node's own certificate can publish on
        its keys)."""
        if order.mutation_seed is None:
            if report.mutation is not None or report.genome != order.genome:
                return "not the body of its job"
        elif report.mutation is None:
            return "a tournament child without its mutation"
        bound = self.fitness_bound
        if not abs(report.fitness) <= bound:
            return f"fitness {report.fitness:g} is beyond what the world allows (|f| <= {bound:g})"
        if report.env_steps > order.steps:
            return f"{report.env_steps} env steps trained, the job allowed {order.steps}"
        return ""

    def _evaluation(self, result: EvalResult) -> None:
        order = self.state.orders.get(result.job)
        key = (result.agent, result.task, result.seed, result.steps)
        if key in self.state.evaluations:
            self._ack(result, result.agent)
        elif (
            not isinstance(order, EvalJob)
            or order.node != result.node
            or (order.agent, order.task, order.seed, order.steps) != key
        ):
            self._reject(result, result.agent, f"job {result.job} was never issued to "
                         f"{result.node} for {result.agent} in {result.task}")  # fmt: skip
        elif not math.isfinite(result.reward):
            self._reject(result, result.agent, "a non-finite score")
        else:
            self._commit(result, publish=False)
            self._ack(result, result.agent)

    def _job_failed(self, failure: JobFailed) -> None:
        state = self.state
        job = state.jobs.get(failure.job)
        if job is None or job.node != failure.node or job.subject != failure.subject:
            self._rejection("failure of a job not held by its sender", "", failure)
            return
        log.warning("%s failed on %s: %s", failure.subject, failure.node, failure.error)
        self._commit(failure, publish=False)
        if job.evaluation is not None and (job.subject, *job.evaluation) in state.eval_given_up:
            log.error("evaluation of %s in %s given up after %d failures", job.subject,
                      job.evaluation[0], self.config.max_attempts)  # fmt: skip
        if job.evaluation is None and state.failed_trainings(job.subject) >= (
            self.config.max_attempts
        ):
            log.error("%s given up after %d failed trainings", job.subject,
                      self.config.max_attempts)  # fmt: skip
            self._commit(
                ChildFailed(
                    run=self.run,
                    child=job.subject,
                    parent=state.evolution.parents.get(job.subject),
                    attempts=state.failed_trainings(job.subject),
                    error=failure.error,
                )
            )

    def _log_births(self) -> None:
        """One line for the births since the last call (a line per birth would be a thousand a
        second on a large cluster)."""
        new = self.state.evolution.born[self.logged_born :]
        if not new:
            return
        fittest = max(new, key=lambda m: m.fitness)
        also = f" (the fittest of {len(new)} new)" if len(new) > 1 else ""
        log.info(
            "born %d/%d: %s fitness %.2f%s",
            self.born,
            self.config.total,
            fittest.agent,
            fittest.fitness,
            also,
        )
        self.logged_born = self.born

    # --- workers and leases ------------------------------------------------------------------

    def _join(self, node: str, role: str) -> None:
        self._leave(node)
        self.alive[node] = role
        self.trainers += role == "trainer"

    def _leave(self, node: str) -> None:
        role = self.alive.pop(node, None)
        self.trainers -= role == "trainer"
        if role is not None:
            self.idle[role].pop(node, None)

    def _liveliness(self, role: str, node: str, up: bool) -> None:
        if up:
            self._join(node, role)
            return
        self._leave(node)
        self.rates.pop(node, None)
        job = self.state.job_of(node)
        if job is not None:
            log.warning("%s left: %s goes back to the queue", node, job.subject)
            self._commit(JobLost(run=self.run, job=job.id, node=node, reason="node left"))

    def _check_leases(self, now: float) -> None:
        for job in list(self.state.jobs.values()):
            if now - self.heard.get(job.id, now) > self.config.lease_s:
                reason = f"no progress for {self.config.lease_s:g} s"
                log.warning("%s: %s; %s goes back to the queue", job.node, reason, job.subject)
                self._commit(JobLost(run=self.run, job=job.id, node=job.node, reason=reason))

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

    def _answer_population(self, query: zenoh.Query) -> None:
        snapshot = self._snapshot()
        query.reply(self.bus.keys.population(), encode(snapshot), encoding=MSGPACK)

    def _status(self) -> RunStatus:
        best = self.state.evolution.best()
        return RunStatus(
            run=self.run,
            born=self.born,
            target=self.config.total,
            best_fitness=None if best is None else best.fitness,
            best_agent=None if best is None else best.agent,
            in_flight=len(self.state.jobs),
            workers_alive=len(self.alive),
            evaluated=self.state.evaluated,
            eval_target=self.state.eval_target,
            failed=len(self.state.failed),
            repeats=self.state.repeats,
            rejected=self.rejected,
            steps_per_s=sum(self.rates.values()),
            done=self.state.finished,
        )

    def _snapshot(self) -> PopulationSnapshot:
        members = tuple(
            Member(agent=m.agent, fitness=m.fitness, parent=m.parent, birth=m.birth)
            for m in self.state.evolution.population
        )
        return PopulationSnapshot(run=self.run, birth_counter=self.born, members=members)

    def _write_results(self) -> None:
        """The best bodies (genome, MJCF, checkpoint, the run's settings) and a summary."""
        evolution = self.state.evolution
        ranked = self.state.best()
        best_dir = self.run_dir / "best"
        settings = json.dumps({"task": self.config.world, "ppo": self.config.training_ppo()
                               .model_dump()}, indent=2)  # fmt: skip
        for rank, member in enumerate(ranked[: max(self.config.eval_top, 3)]):
            folder = best_dir / f"{rank + 1:02d}-{member.agent}"
            folder.mkdir(parents=True, exist_ok=True)
            genome = evolution.genomes[member.agent]
            write_atomic(folder / "genome.json", genome.model_dump_json(indent=2) + "\n")
            write_atomic(folder / "body.xml", to_mjcf(genome))
            write_atomic(folder / "training.json", settings + "\n")
            checkpoint = self.checkpoints.path(member.agent)
            if checkpoint.exists():
                write_atomic(folder / "checkpoint.pt", checkpoint.read_bytes())
        summary = {
            "run": self.run,
            "profile": self.config.model_dump(),
            "born": self.born,
            "failed": sorted(self.state.failed),
            "best": [vars(m) for m in ranked[:10]],
            "evaluations": [
                r.model_dump(exclude={"curve"}) for r in self.state.evaluations.values()
            ],
        }
        write_atomic(self.run_dir / "summary.json", json.dumps(summary, indent=2, default=str))
        log.info("run %s finished: %d born, results in %s", self.run, self.born, self.run_dir)


def _log_failed_link(done: Future[None]) -> None:
    if done.exception() is not None:
        log.error("a repeat's checkpoint could not be linked: %s", done.exception())


def check_jobs(run: str, config: EvolutionConfig) -> None:
    """Exit with the reason if a job of this configuration would not be a valid message, so
    every value a job carries is checked before anything starts."""
    try:
        ids = {"run": run, "job": "check", "node": "check", "genome": GENOME}
        TrainJob(**ids, child="check", task=config.world, ppo=config.training_ppo(),
                 lease_s=config.lease_s)  # fmt: skip
        for task in config.eval_tasks:
            for seed in range(config.eval_seeds):
                EvalJob(**ids, agent="check", task=task, ppo=config.evaluation_ppo(task, seed),
                        lease_s=config.lease_s)  # fmt: skip
    except (ValueError, ValidationError) as error:
        raise SystemExit(f"derl: run {run!r} cannot start: {error}") from None


def serve(
    run: str,
    run_dir: Path,
    config: object,
    options: ZenohOptions,
    kind: type[Coordinator] = Coordinator,
) -> bool:
    """The coordinator (of `kind`, started with `config`: a run's EvolutionConfig) of `run`
    until the run is finished (True) or it is stopped (False); the run directory is locked
    from before its journal is read until the end."""
    try:
        with lock_run_dir(run_dir):
            coordinator = kind(run, run_dir, config)
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: coordinator.stop.set())
            return coordinator.serve(options)
    except RunDirLocked as locked:
        raise SystemExit(f"derl: {locked}") from None
