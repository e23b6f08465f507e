"""Trainer and evaluator nodes: announce themselves, take a job, learn, deliver until acknowledged.

A worker holds a liveliness token for its whole life and publishes WorkerReady when idle, again
after 1, 2, 4, then every 8 s while no job comes (`ready_wait`: the coordinator sends a job to an
idle worker that asked as soon as there is one). The first ask goes out once the coordinator's
subscription is known here: one sent before is lost, and a neighbour may take the job meanwhile.
It trains one job at a time with `derl.lifetime`, the job's body (the coordinator decides every
body) and the job's own PPO configuration (one training per process; a child that inherits its
parent's weights starts from the parent's checkpoint, asked of the coordinator on
``checkpoint/<parent>`` and checked against the job's SHA-256), reports progress every
second (the coordinator's lease on the job), and re-sends its result every second until the
coordinator acknowledges it, so a coordinator restart loses nothing. A Reject makes it drop the
result, a Cancel of its job stops the training, and a training that raises is reported as
JobFailed; each time it asks for work again. Every key it publishes on carries its node id. It
stops on SIGTERM or SIGINT, or when the run is done. An idle worker that has heard no
coordinator of its run for `UNHEARD_S` (the coordinator publishes the run's status every second)
says so once: a mistyped run id or endpoint must not look like a quiet run.
"""

from __future__ import annotations

import hashlib
import logging
import os
import queue
import signal
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

from derl.extensions import REGISTRIES
from derl.lifetime import LifetimeResult, learn
from derl.messages import (
    Ack,
    Cancel,
    Curve,
    EvalJob,
    EvalResult,
    FitnessReport,
    JobFailed,
    Reject,
    RunStatus,
    TrainJob,
    TrainProgress,
    WorkerReady,
)
from derl.metrics import TensorBoardRun, record
from derl.nodes.runtime.bus import Bus, ZenohOptions, matched, open_session
from derl.plugins import PluginError, check_plugins
from derl.rl import Progress

log = logging.getLogger("derl.worker")

READY_PERIOD_S = (1.0, 8.0)  # the wait after the first ask while idle, doubled up to the last
HEARD_POLL_S = 0.01  # how often a worker looks whether its WorkerReady would be heard
PROGRESS_PERIOD_S = 1.0
RESEND_PERIOD_S = 1.0
UNHEARD_S = 10.0  # an idle worker that heard no status of its run this long says so
PARENT_WAIT_S = 60.0  # how long a trainer asks for a parent's checkpoint before the job fails
PARENT_ASK_S = (5.0, 0.5)  # a query's timeout, and the pause before the next


def ready_wait(asks: int) -> float:
    """How long an idle worker waits for a job after its `asks`-th unanswered WorkerReady (0 the
    first) before it asks again: the coordinator sends a job to a worker that asked as soon as
    there is one, so asking again only recovers from a lost message or a restarted coordinator,
    and 10,000 idle workers no longer ask 10,000 times a second."""
    return min(READY_PERIOD_S[0] * 2.0**asks, READY_PERIOD_S[1])


class Stopped(Exception):
    """The node was asked to stop in the middle of a job."""


class Cancelled(Exception):
    """The coordinator cancelled the job in progress."""


class NoParentWeights(Exception):
    """The parent's checkpoint a job inherits did not come, or is not the one the job names."""


class Worker:
    """Worker `node` of `run` in `role`, training on `nthread` threads; `clock` times its waits,
    its progress and its silence (a test moves one by hand)."""

    def __init__(
        self,
        run: str,
        node: str,
        role: Literal["trainer", "evaluator"],
        nthread: int = 1,
        clock: Callable[[], float] = time.monotonic,
        tensorboard: Path | None = None,
    ) -> None:
        self.run, self.node, self.role, self.nthread = run, node, role, nthread
        self.clock = clock
        self.tensorboard = tensorboard  # each training's records: LOGDIR/<run>/children/<agent>
        self.stop = threading.Event()
        self.run_finished = threading.Event()
        self.finished_jobs: set[str] = set()  # a copy sent again is not trained twice
        self.cancelled: set[str] = set()
        self.heard_at = self.clock()  # when the run's status was last heard (or the start)
        self.unheard = False  # said that no coordinator is heard (until one is)
        self.unfit = False  # refused a job for its plugins (said once)

    def serve(self, options: ZenohOptions, max_jobs: int | None = None) -> None:
        with open_session(options) as session:
            bus = Bus(session, self.run)
            self.bus = bus
            token = bus.token(self.role, self.node)
            kinds = (TrainJob,) if self.role == "trainer" else (EvalJob,)
            jobs: queue.Queue[TrainJob | EvalJob] = queue.Queue()
            bus.subscribe(bus.keys.job(self.node), self._order(jobs), (*kinds, Cancel))
            answers = bus.inbox(bus.keys.ack(self.node), (Ack, Reject))
            bus.subscribe(bus.keys.status(), self._status, (RunStatus,))
            self.asking = session.declare_publisher(bus.keys.ready(self.node))
            log.info("%s %s ready for run %s", self.role, self.node, self.run)
            asks = 0  # WorkerReady sent since the last job
            while not self._over(max_jobs):
                job = self._next_job(jobs, ready_wait(asks))
                asks = asks + 1 if job is None else 0
                if job is None:
                    self._say_if_unheard()
                    continue
                if not self._fit_for(job):
                    self.finished_jobs.add(job.job)
                    continue
                try:
                    result = self._work(job)
                except Stopped:
                    break
                except Cancelled:
                    log.info("%s: %s cancelled by the coordinator", self.node, job.job)
                    self.finished_jobs.add(job.job)
                    continue
                except Exception as error:  # a failed training is reported, never fatal
                    log.exception("%s: %s failed", self.node, job.job)
                    self._failed(job, f"{type(error).__name__}: {error}")
                    self.finished_jobs.add(job.job)
                    continue
                self._deliver(result, answers)
                self.finished_jobs.add(job.job)
            token.undeclare()

    def _order(self, jobs: queue.Queue) -> Callable[[object], None]:
        def on_order(msg: object) -> None:
            if isinstance(msg, Cancel):
                self.cancelled.add(msg.job)
            else:
                jobs.put(msg)

        return on_order

    def _over(self, max_jobs: int | None) -> bool:
        limit = max_jobs is not None and len(self.finished_jobs) >= max_jobs
        return self.stop.is_set() or self.run_finished.is_set() or limit

    def _status(self, status: RunStatus) -> None:
        self.heard_at = self.clock()
        if self.unheard:
            self.unheard = False
            log.info("%s: the coordinator of run %s is heard", self.node, self.run)
        if status.done:
            self.run_finished.set()

    def _say_if_unheard(self) -> None:
        silent = self.clock() - self.heard_at
        if silent >= UNHEARD_S and not self.unheard:
            self.unheard = True
            log.warning("%s: no coordinator of run %s heard for %.0f s (none publishes derl/%s/"
                        "status): is it running? check --run and --connect", self.node, self.run,
                        silent, self.run)  # fmt: skip

    def _next_job(self, jobs: queue.Queue, wait_s: float) -> TrainJob | EvalJob | None:
        """Ask for work, then wait up to `wait_s` for a job (None: none came, or the worker
        stops)."""
        ready = WorkerReady(
            run=self.run,
            node=self.node,
            role=self.role,
            host=socket.gethostname()[:253] or "host",
            pid=os.getpid(),
            nthread=self.nthread,
        )
        deadline = self.clock() + READY_PERIOD_S[0]
        while not matched(self.asking) and self.clock() < deadline and not self.stop.is_set():
            time.sleep(HEARD_POLL_S)  # no coordinator would hear it yet
        self.bus.publish(ready)
        deadline = self.clock() + wait_s
        while True:
            remaining = deadline - self.clock()
            if remaining <= 0 or self._over(None):
                return None
            try:  # in slices, so that a stop or the run's end is seen within one
                job = jobs.get(timeout=min(remaining, READY_PERIOD_S[0]))
                break
            except queue.Empty:
                continue
        if job.job in self.finished_jobs or job.job in self.cancelled:
            log.info("%s: %s was sent again after it was done: ignored", self.node, job.job)
            return None
        return job

    def _failed(self, job: TrainJob | EvalJob, text: str, unfit: bool = False) -> None:
        """`job` failed here (`unfit`: this node cannot run the run's jobs at all)."""
        self.bus.publish(JobFailed(run=self.run, job=job.job, node=self.node, agent=job.agent,
                                   error=text[:1000], unfit=unfit))  # fmt: skip

    def _fit_for(self, job: TrainJob | EvalJob) -> bool:
        """Whether this process holds the job's plugins, each in the job's version; if not, the
        job is refused (`JobFailed.unfit`: the coordinator sends no more) and the reason logged
        once."""
        try:
            check_plugins(job.plugins, REGISTRIES)
        except PluginError as error:
            text = f"{self.node} {error}"
            if not self.unfit:
                log.error("%s; refusing the run's jobs (install the plugin as on the other "
                          "nodes: docs/extending.md)", text)  # fmt: skip
            self.unfit = True
            self._failed(job, text, unfit=True)
            return False
        return True

    def _work(self, job: TrainJob | EvalJob) -> FitnessReport | EvalResult:
        log.info("%s: %s of %s on %s (%d steps)", self.node, job.job, job.agent, job.task,
                 job.steps)  # fmt: skip
        last = 0.0
        board = self._board(job)

        def progress(p: Progress) -> None:
            nonlocal last
            if self.stop.is_set():
                raise Stopped
            if job.job in self.cancelled:
                raise Cancelled
            if board is not None:
                board.write(record(p))
            now = self.clock()
            if now - last >= PROGRESS_PERIOD_S or p.iteration == p.iterations:
                last = now
                self.bus.publish(
                    TrainProgress(
                        run=self.run,
                        agent=job.agent,
                        job=job.job,
                        node=self.node,
                        env_steps=p.env_steps,
                        total_steps=job.steps,
                        recent_return=p.recent_return,
                        steps_per_s=p.steps_per_second,
                    )
                )

        parent = None
        if isinstance(job, TrainJob) and job.inherit is not None:
            parent = (job.inherit.genome, self._parent_weights(job))
        try:
            summary, result = learn(
                job.genome, job.task, job.ppo, progress, nthread=self.nthread, parent=parent
            )
        finally:
            if board is not None:
                board.close()
        curve = Curve(env_steps=summary.curve_steps, returns=summary.curve_returns)
        if isinstance(job, TrainJob):
            checkpoint = result.checkpoint.to_bytes()
            return self._fitness_report(job, summary, curve, checkpoint)
        return EvalResult(
            run=self.run,
            agent=job.agent,
            task=job.task,
            seed=job.seed,
            steps=job.steps,
            reward=summary.fitness,
            cost_of_work=summary.cost_of_work,
            curve=curve,
            node=self.node,
            job=job.job,
        )

    def _board(self, job: TrainJob | EvalJob) -> TensorBoardRun | None:
        """Where a training's records go in TensorBoard (`derl.metrics`, as `derl train
        --tensorboard` writes them), if this trainer writes them: LOGDIR/<run>/children/<agent>
        (a second training of the child goes on after the first's last step)."""
        if self.tensorboard is None or not isinstance(job, TrainJob):
            return None
        return TensorBoardRun(self.tensorboard / self.run / "children" / job.agent)

    def _parent_weights(self, job: TrainJob) -> bytes:
        """The checkpoint of `job`'s parent, asked of the coordinator (which answers once the
        file is on its disk) until it comes, for up to `PARENT_WAIT_S`; `NoParentWeights` if it
        does not, or if its SHA-256 is not the job's."""
        assert job.inherit is not None and job.parent is not None
        key = self.bus.keys.checkpoint(job.parent)
        deadline = self.clock() + PARENT_WAIT_S
        while not self.stop.is_set():
            for reply in self.bus.session.get(key, timeout=PARENT_ASK_S[0]):
                if reply.ok is None:
                    continue
                data = reply.ok.payload.to_bytes()
                if hashlib.sha256(data).digest() != job.inherit.sha256:
                    raise NoParentWeights(
                        f"the checkpoint of {job.parent} that came has SHA-256 "
                        f"{hashlib.sha256(data).hexdigest()}, the job names "
                        f"{job.inherit.sha256.hex()}"
                    )
                return data
            if self.clock() >= deadline:
                raise NoParentWeights(
                    f"no checkpoint of {job.parent} came from the coordinator on {key} in "
                    f"{PARENT_WAIT_S:.0f} s"
                )
            time.sleep(PARENT_ASK_S[1])
        raise Stopped

    def _fitness_report(
        self, job: TrainJob, summary: LifetimeResult, curve: Curve, checkpoint: bytes
    ) -> FitnessReport:
        return FitnessReport(
            run=self.run,
            agent=job.agent,
            job=job.job,
            node=self.node,
            genome=job.genome,
            fitness=summary.fitness,
            fitness_source=summary.fitness_source,
            fitness_episodes=summary.fitness_episodes,
            curve=curve,
            energy=summary.energy,
            cost_of_work=summary.cost_of_work,
            mass=summary.mass,
            episodes=summary.episodes,
            env_steps=summary.env_steps,
            constraint_rows=summary.constraint_rows,
            wall_s=summary.wall_time_s,
            steps_per_s=summary.steps_per_second,
            checkpoint=checkpoint,
        )

    def _deliver(self, result: FitnessReport | EvalResult, answers: queue.Queue) -> None:
        """Publish `result` every second until it is acknowledged or rejected (or the node
        stops, or the coordinator cancels the job). Answers that came before the first publish
        are about someone else's report for this job (one forged under this node's name, say),
        never about this one: they are dropped."""
        while True:
            try:
                answers.get_nowait()
            except queue.Empty:
                break
        while not self.stop.is_set() and result.job not in self.cancelled:
            self.bus.publish(result)
            deadline = self.clock() + RESEND_PERIOD_S
            while (wait := deadline - self.clock()) > 0:
                try:
                    answer = answers.get(timeout=wait)
                except queue.Empty:
                    break
                if answer.job != result.job:
                    continue
                if isinstance(answer, Reject):
                    log.warning("%s: %s rejected: %s", self.node, result.job, answer.reason)
                else:
                    log.info("%s: %s acknowledged", self.node, result.job)
                return


def serve(
    run: str,
    node: str,
    role: Literal["trainer", "evaluator"],
    options: ZenohOptions,
    nthread: int = 1,
    tensorboard: Path | None = None,
) -> None:
    worker = Worker(run, node, role, nthread, tensorboard=tensorboard)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: worker.stop.set())
    worker.serve(options)
