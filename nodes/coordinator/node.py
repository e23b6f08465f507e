"""The coordinator node: owns the population, hands out jobs, journals everything it accepts.

It runs one loop over an inbox that every subscription feeds, so the state has one writer.
Every message it accepts or sends is first appended to the run's MCAP journal and applied to
`CoordinatorState` (the same `apply` that rebuilds the state on restart), then published. It
takes what the inbox holds as a group (group commit): the group's messages are journaled, the
journal is flushed once, and only then is what they made the coordinator say published, so
nothing is seen that a crash could forget, at one file write per group instead of per message. A
trainer that loses its liveliness token, or sends no progress for its job's lease, loses the
job; the child goes to the next ready worker. Fitness reports are acknowledged when accepted, and
also when they repeat a birth or come for a job that was taken back (so the sender stops),
never for a job that was never issued to that node.
"""

from __future__ import annotations

import gc
import json
import logging
import queue
import signal
import threading
import time
from concurrent.futures import Future
from pathlib import Path

from derl.evolution import EvolutionConfig
from derl.unimal import Genome, to_mjcf
from messages import (
    Ack,
    EvalJob,
    EvalResult,
    FitnessReport,
    Member,
    MessageBase,
    PopulationSnapshot,
    RunStatus,
    TrainJob,
    TrainProgress,
    WorkerReady,
    encode,
)
from nodes.coordinator.state import CoordinatorState, tournament_message
from nodes.journal.segments import Journal, replay, segments
from nodes.runtime.bus import Bus, ZenohOptions, open_session
from nodes.runtime.checkpoints import CheckpointFiles

log = logging.getLogger("derl.coordinator")

STATUS_PERIOD_S = 1.0
SNAPSHOT_PERIOD_S = 5.0
DONE_ANNOUNCEMENTS = 5
GROUP_S = 0.005  # the longest a group is handled before its journal flush and replies
PROFILE_FILE = "profile.json"
INITIAL_FILE = "initial_population.json"


class Coordinator:
    def __init__(self, run: str, run_dir: Path, config: EvolutionConfig) -> None:
        self.run, self.run_dir, self.config = run, run_dir, config
        run_dir.mkdir(parents=True, exist_ok=True)
        self._check_profile()
        self.state = CoordinatorState.start(config, self._saved_initial_population())
        self._save_initial_population()
        replayed = 0
        if segments(run_dir):
            for msg in replay(run_dir):
                self.state.apply(msg)
                replayed += 1
        self.replayed = replayed
        self.logged_born = self.born
        self.journal = Journal(run_dir)
        self.checkpoints = CheckpointFiles(run_dir)
        # published after the journal flush (and, for an Ack, once its checkpoint is on disk)
        self.outbox: list[tuple[MessageBase, bytes, Future[None] | None]] = []
        now = time.monotonic()
        self.heard = {job: now for job in self.state.jobs}  # leases restart on a restart
        self.alive: dict[str, str] = {}  # node -> role
        self.rates: dict[str, float] = {}  # node -> steps/s
        self.stop = threading.Event()
        log.info("run %s: %d journaled messages replayed, %d born", run, replayed, self.born)

    @property
    def born(self) -> int:
        return len(self.state.evolution.born)

    # --- setup -------------------------------------------------------------------------------

    def _check_profile(self) -> None:
        path = self.run_dir / PROFILE_FILE
        if path.exists():
            saved = EvolutionConfig.model_validate_json(path.read_text())
            if saved != self.config:
                raise SystemExit(
                    f"derl: {self.run_dir} holds a run with another profile ({saved.name}); "
                    "resume it with the same settings or use a new --run-dir"
                )
        else:
            path.write_text(self.config.model_dump_json(indent=2) + "\n")

    def _saved_initial_population(self) -> list[Genome] | None:
        """The initial bodies, if this run drew them before (else `Evolution` draws them)."""
        path = self.run_dir / INITIAL_FILE
        if not path.exists():
            return None
        return [Genome.model_validate(g) for g in json.loads(path.read_text())]

    def _save_initial_population(self) -> None:
        """Keep the initial bodies as a fact of the run (drawing them again is slow)."""
        path = self.run_dir / INITIAL_FILE
        if path.exists():
            return
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps([c.genome.model_dump() for c in self.state.evolution.initial]))
        tmp.replace(path)

    # --- the loop ----------------------------------------------------------------------------

    def serve(self, options: ZenohOptions) -> None:
        with open_session(options) as session:
            bus = Bus(session, self.run)
            inbox: queue.Queue[tuple[str, object]] = queue.Queue()
            for kind, types in (
                ("ready", (WorkerReady,)),
                ("fitness", (FitnessReport,)),
                ("progress", (TrainProgress,)),
                ("eval", (EvalResult,)),
            ):
                bus.subscribe(bus.keys.all(kind), lambda m: inbox.put(("msg", m)), types)
            bus.watch_alive(lambda role, node, up: inbox.put(("alive", (role, node, up))))
            self.bus = bus
            next_status = next_snapshot = 0.0
            announced = 0
            while not self.stop.is_set():
                try:
                    self._take(*inbox.get(timeout=0.2))
                    until = time.monotonic() + GROUP_S
                    while time.monotonic() < until:
                        self._take(*inbox.get_nowait())
                except queue.Empty:
                    pass
                self._flush()
                now = time.monotonic()
                if now >= next_status:
                    # The state only grows (every body, every job) and its handling makes no
                    # cyclic garbage, so once a second everything alive leaves the cyclic GC's
                    # care: else its full passes over a large run's state stall the loop for
                    # hundreds of ms (measured: 0.5 s at 20k births).
                    gc.freeze()
                    self._log_births()
                    self._check_leases(now)
                    bus.publish(self._status(), reliable=False)
                    next_status = now + STATUS_PERIOD_S
                    if self.state.finished:
                        announced += 1
                        if announced == 1:
                            self._write_results()
                        if announced >= DONE_ANNOUNCEMENTS:
                            break
                if now >= next_snapshot:
                    bus.publish(self._snapshot(), reliable=False)
                    next_snapshot = now + SNAPSHOT_PERIOD_S
        self.checkpoints.close()
        self.journal.close()

    def _take(self, kind: str, item: object) -> None:
        try:
            if kind == "msg":
                self._handle(item)
            elif kind == "alive":
                self._liveliness(*item)
        except Exception:  # one message must never stop the run: log it and go on
            self.bus.rejected["handler error"] += 1
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
        """The group's messages into the journal file, then its replies onto the bus."""
        self.journal.flush()
        for msg, data, after in self.outbox:
            failed = None if after is None else after.exception()
            if failed is None:
                self.bus.publish(msg, data=data)
            else:  # unacknowledged: its trainer sends the report again, and the write is retried
                log.error("%s not acknowledged: its checkpoint was not written: %s", msg, failed)
        self.outbox.clear()

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

    # --- assignments -------------------------------------------------------------------------

    def _ready(self, ready: WorkerReady) -> None:
        self.alive.setdefault(ready.node, ready.role)
        current = self.state.job_of(ready.node)
        if current is not None:  # it missed its job (e.g. the coordinator restarted)
            self.outbox.append((current.order, encode(current.order), None))
        elif ready.role == "trainer":
            self._assign_training(ready.node)
        else:
            self._assign_evaluation(ready.node)

    def _assign_training(self, node: str) -> None:
        state, evolution = self.state, self.state.evolution
        if state.waiting:
            child = state.waiting[0]
        elif state.wants_tournament():
            decided = evolution.tournament()
            self._commit(tournament_message(self.run, decided))
            child = decided.child
        else:
            return
        genome, mutation_seed = evolution.to_train(child)
        job = TrainJob(
            run=self.run,
            job=state.next_job_id(child),
            child=child,
            node=node,
            genome=genome,
            task=self.config.world,
            steps=self.config.train_steps,
            seed=self.config.training_seed,
            parent=evolution.parents[child],
            mutation_seed=mutation_seed,
            lease_s=self.config.lease_s,
            num_envs=self.config.num_envs,
        )
        self._commit(job)
        self.heard[job.job] = time.monotonic()
        log.debug("%s -> %s (%s)", child, node, job.job)

    def _assign_evaluation(self, node: str) -> None:
        key = self.state.next_evaluation()
        if key is None:
            return
        agent, task, seed = key
        job = EvalJob(
            run=self.run,
            job=f"e-{agent}-{task}-{seed}.{len(self.state.issued) + 1}",
            agent=agent,
            node=node,
            genome=self.state.evolution.genomes[agent],
            task=task,
            seed=seed,
            steps=self.config.eval_steps,
            lease_s=self.config.lease_s,
            num_envs=self.config.num_envs,
        )
        self._commit(job)
        self.heard[job.job] = time.monotonic()

    # --- results -----------------------------------------------------------------------------

    def _ack(
        self, msg: FitnessReport | EvalResult, subject: str, after: Future[None] | None = None
    ) -> None:
        ack = Ack(run=self.run, of=msg.type, job=msg.job, child=subject, node=msg.node)
        self._commit(ack, after=after)

    def _fitness(self, report: FitnessReport) -> None:
        state = self.state
        job = state.jobs.get(report.job)
        if report.child in state.evolution.fitness:
            log.info("%s already born: repeated report acknowledged", report.child)
            saved = None  # a crash (or a failed write) may have lost its checkpoint file
            if report.checkpoint and not self.checkpoints.path(report.child).exists():
                saved = self.checkpoints.save(report.child, report.checkpoint)
            self._ack(report, report.child, after=saved)
        elif job is not None and job.node == report.node and job.subject == report.child:
            wrong = self._wrong_body(report)
            if wrong:
                self.bus.rejected["wrong body"] += 1
                log.warning("rejected fitness of %s from %s: %s", report.child, report.node, wrong)
                return
            saved = self.checkpoints.save(report.child, report.checkpoint)
            self._commit(report.model_copy(update={"checkpoint": b""}), publish=False)
            log.debug("born %s fitness %.2f", report.child, report.fitness)
            self._ack(report, report.child, after=saved)
        elif state.issued_to(report.job, report.node):
            log.info(
                "report for %s taken back from %s: acknowledged, not used", report.job, report.node
            )
            self._ack(report, report.child)
        else:
            self.bus.rejected["unknown job"] += 1
            log.warning(
                "rejected fitness of %s: job %s was never issued to %s",
                report.child,
                report.job,
                report.node,
            )

    def _wrong_body(self, report: FitnessReport) -> str:
        """Why the body in `report` cannot be the one its job asked for ("" if it can).

        A child bred by its trainer is taken as reported (breeding is deterministic and trainers
        are trusted like their fitness; TLS and access control keep others off the bus)."""
        job = self.state.jobs[report.job].order
        assert isinstance(job, TrainJob)
        if job.mutation_seed is None:
            if report.mutation is not None or report.genome != job.genome:
                return "not the body of its job"
        elif report.mutation is None:
            return "a tournament child without its mutation"
        return ""

    def _evaluation(self, result: EvalResult) -> None:
        job = self.state.jobs.get(result.job)
        key = (result.agent, result.task, result.seed)
        if self.state.evaluations.get(key) is not None:
            self._ack(result, result.agent)
        elif job is not None and job.node == result.node:
            self._commit(result, publish=False)
            self._ack(result, result.agent)
        elif self.state.issued_to(result.job, result.node):
            self._ack(result, result.agent)
        else:
            self.bus.rejected["unknown job"] += 1
            log.warning(
                "rejected evaluation: job %s was never issued to %s", result.job, result.node
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

    def _liveliness(self, role: str, node: str, up: bool) -> None:
        if up:
            self.alive[node] = role
            return
        self.alive.pop(node, None)
        self.rates.pop(node, None)
        job = self.state.job_of(node)
        if job is not None:
            log.warning("%s left: %s goes back to the queue", node, job.subject)
            self.state.lose(job.job)

    def _check_leases(self, now: float) -> None:
        for job in list(self.state.jobs.values()):
            if now - self.heard.get(job.job, now) > self.config.lease_s:
                log.warning(
                    "%s silent for %.0f s: %s goes back to the queue",
                    job.node,
                    self.config.lease_s,
                    job.subject,
                )
                self.state.lose(job.job)

    # --- what the run looks like -------------------------------------------------------------

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
            rejected=sum(self.bus.rejected.values()),
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
        """The best bodies (genome, MJCF, checkpoint) and a summary, in the run directory."""
        evolution = self.state.evolution
        ranked = sorted(evolution.born, key=lambda m: m.fitness, reverse=True)
        best_dir = self.run_dir / "best"
        for rank, member in enumerate(ranked[: max(self.config.eval_top, 3)]):
            folder = best_dir / f"{rank + 1:02d}-{member.agent}"
            folder.mkdir(parents=True, exist_ok=True)
            genome = evolution.genomes[member.agent]
            (folder / "genome.json").write_text(genome.model_dump_json(indent=2) + "\n")
            (folder / "body.xml").write_text(to_mjcf(genome))
            checkpoint = self.checkpoints.path(member.agent)
            if checkpoint.exists():
                (folder / "checkpoint.pt").write_bytes(checkpoint.read_bytes())
        summary = {
            "run": self.run,
            "profile": self.config.model_dump(),
            "born": self.born,
            "best": [vars(m) for m in ranked[:10]],
            "evaluations": [
                r.model_dump(exclude={"curve"}) for r in self.state.evaluations.values() if r
            ],
        }
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
        log.info("run %s finished: %d born, results in %s", self.run, self.born, self.run_dir)


def serve(run: str, run_dir: Path, config: EvolutionConfig, options: ZenohOptions) -> None:
    coordinator = Coordinator(run, run_dir, config)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: coordinator.stop.set())
    coordinator.serve(options)
