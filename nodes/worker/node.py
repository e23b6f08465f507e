"""Trainer and evaluator nodes: announce themselves, take a job, learn, deliver until acknowledged.

A worker holds a liveliness token for its whole life, publishes WorkerReady every second while
idle, trains one job at a time with `derl.lifetime` (one training per process; a tournament's
child is first bred from its parent's body with `derl.evolution.breed`), reports progress
every second (the coordinator's lease on the job), and re-sends its result every second until
the coordinator acknowledges it, so a coordinator restart loses nothing. It stops on SIGTERM or
SIGINT, or when the run's status says it is done.
"""

from __future__ import annotations

import logging
import os
import queue
import signal
import socket
import threading
import time
from typing import Literal

from derl.evolution import breed
from derl.lifetime import LifetimeResult, learn, ppo_config
from derl.rl import Progress
from derl.unimal import Genome, Mutation
from messages import (
    Ack,
    Curve,
    EvalJob,
    EvalResult,
    FitnessReport,
    RunStatus,
    TrainJob,
    TrainProgress,
    WorkerReady,
)
from nodes.runtime.bus import Bus, ZenohOptions, open_session

log = logging.getLogger("derl.worker")

READY_PERIOD_S = 1.0
PROGRESS_PERIOD_S = 1.0
RESEND_PERIOD_S = 1.0


class Stopped(Exception):
    """The node was asked to stop in the middle of a job."""


class Worker:
    def __init__(
        self, run: str, node: str, role: Literal["trainer", "evaluator"], nthread: int = 1
    ) -> None:
        self.run, self.node, self.role, self.nthread = run, node, role, nthread
        self.stop = threading.Event()
        self.run_done = threading.Event()
        self.done: set[str] = set()  # jobs trained: a copy sent again is not trained twice

    def serve(self, options: ZenohOptions, max_jobs: int | None = None) -> None:
        with open_session(options) as session:
            bus = Bus(session, self.run)
            self.bus = bus
            token = bus.token(self.role, self.node)
            kinds = (TrainJob,) if self.role == "trainer" else (EvalJob,)
            jobs = bus.inbox(bus.keys.job(self.node), kinds)
            acks = bus.inbox(bus.keys.ack(self.node), (Ack,))
            bus.subscribe(bus.keys.status(), self._status, (RunStatus,))
            log.info("%s %s ready for run %s", self.role, self.node, self.run)
            while not self._finished(max_jobs):
                job = self._next_job(jobs)
                if job is None:
                    continue
                try:
                    result = self._work(job)
                except Stopped:
                    break
                self._deliver(result, acks)
                self.done.add(job.job)
            token.undeclare()

    def _finished(self, max_jobs: int | None) -> bool:
        limit = max_jobs is not None and len(self.done) >= max_jobs
        return self.stop.is_set() or self.run_done.is_set() or limit

    def _status(self, status: RunStatus) -> None:
        if status.done:
            self.run_done.set()

    def _next_job(self, jobs: queue.Queue) -> TrainJob | EvalJob | None:
        ready = WorkerReady(
            run=self.run,
            node=self.node,
            role=self.role,
            host=socket.gethostname()[:253] or "host",
            pid=os.getpid(),
            nthread=self.nthread,
        )
        self.bus.publish(ready)
        try:
            job = jobs.get(timeout=READY_PERIOD_S)
        except queue.Empty:
            return None
        if job.job in self.done:
            log.info("%s: %s was sent again after it was done: ignored", self.node, job.job)
            return None
        return job

    def _work(self, job: TrainJob | EvalJob) -> FitnessReport | EvalResult:
        subject = job.child if isinstance(job, TrainJob) else job.agent
        log.info("%s: %s of %s on %s (%d steps)", self.node, job.job, subject, job.task, job.steps)
        last = 0.0

        def progress(p: Progress) -> None:
            nonlocal last
            if self.stop.is_set():
                raise Stopped
            now = time.monotonic()
            if now - last >= PROGRESS_PERIOD_S or p.iteration == p.iterations:
                last = now
                self.bus.publish(
                    TrainProgress(
                        run=self.run,
                        child=subject,
                        job=job.job,
                        node=self.node,
                        env_steps=p.env_steps,
                        total_steps=job.steps,
                        recent_return=p.recent_return,
                        steps_per_s=p.steps_per_second,
                    ),
                    reliable=False,
                )

        genome, mutation = job.genome, None
        if isinstance(job, TrainJob) and job.mutation_seed is not None:
            genome, mutation = breed(job.genome, job.mutation_seed)
            log.info("%s: %s bred from %s by %s", self.node, subject, job.parent, mutation.op)
        config = ppo_config(job.task, job.steps, job.seed, num_envs=job.num_envs)
        summary, result = learn(genome, job.task, config, progress, nthread=self.nthread)
        curve = Curve(env_steps=summary.curve_steps, returns=summary.curve_returns)
        if isinstance(job, TrainJob):
            checkpoint = result.checkpoint.to_bytes()
            return self._fitness_report(job, genome, mutation, summary, curve, checkpoint)
        return EvalResult(
            run=self.run,
            agent=job.agent,
            task=job.task,
            seed=job.seed,
            reward=summary.fitness,
            cost_of_work=summary.cost_of_work,
            curve=curve,
            node=self.node,
            job=job.job,
        )

    def _fitness_report(
        self,
        job: TrainJob,
        genome: Genome,
        mutation: Mutation | None,
        summary: LifetimeResult,
        curve: Curve,
        checkpoint: bytes,
    ) -> FitnessReport:
        return FitnessReport(
            run=self.run,
            child=job.child,
            job=job.job,
            node=self.node,
            genome=genome,
            mutation=None if mutation is None else mutation.op,
            mutation_detail="" if mutation is None else mutation.detail,
            fitness=summary.fitness,
            fitness_source=summary.fitness_source,
            fitness_episodes=summary.fitness_episodes,
            curve=curve,
            energy=summary.energy,
            cost_of_work=summary.cost_of_work,
            mass=summary.mass,
            episodes=summary.episodes,
            env_steps=summary.env_steps,
            wall_s=summary.wall_time_s,
            steps_per_s=summary.steps_per_second,
            checkpoint=checkpoint,
        )

    def _deliver(self, result: FitnessReport | EvalResult, acks: queue.Queue) -> None:
        """Publish `result` every second until it is acknowledged (or the node stops)."""
        while not self.stop.is_set():
            self.bus.publish(result)
            deadline = time.monotonic() + RESEND_PERIOD_S
            while (wait := deadline - time.monotonic()) > 0:
                try:
                    ack = acks.get(timeout=wait)
                except queue.Empty:
                    break
                if ack.job == result.job:
                    log.info("%s: %s acknowledged", self.node, result.job)
                    return


def serve(
    run: str,
    node: str,
    role: Literal["trainer", "evaluator"],
    options: ZenohOptions,
    nthread: int = 1,
) -> None:
    worker = Worker(run, node, role, nthread)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: worker.stop.set())
    worker.serve(options)
