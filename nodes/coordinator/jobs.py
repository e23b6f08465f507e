"""The job book: the jobs in flight and the evaluation stage, kept alike by every coordinator.

Every coordinator's state (`EvolutionState` for a run, `StudyState` for a study) is a `JobBook`:
the journal's fold (`RunHistory`) plus the jobs in flight (who holds each, the order as it was
sent), the orders of subjects with no result yet (a late result is checked against its order),
and the evaluations: planned, waiting for an evaluator, given up after `max_attempts` failed jobs,
done. Its handlers are the only way it changes, both live and when a restarted coordinator replays
its journal: an EvalJob puts a job in flight, an EvalResult completes an evaluation, a Cancel ends
a job, a JobLost or a JobFailed takes a job back (its agent waits for the next worker). What
each state plans (`_plan_evaluations`), how it orders an evaluation (`evaluation_order`) and when
it is over (`finished`) is its own; time (leases) and the checks of incoming messages are the
node's business.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from derl.messages import Cancel, EvalJob, EvalResult, JobFailed, JobLost, MessageBase, TrainJob
from derl.messages.dispatch import handles
from derl.nodes.journal.history import EvalKey, RunHistory
from derl.rl import PPOConfig
from derl.unimal import Genome


@dataclass
class Job:
    """An assignment in flight."""

    id: str
    agent: str  # the child (training) or agent (evaluation)
    node: str
    order: TrainJob | EvalJob  # as sent (sent again to a worker that missed it)
    evaluation: tuple[str, int, int] | None = None  # (task, seed, steps) for an evaluation


class JobBook(RunHistory, ABC):
    """The jobs in flight and the evaluations of a coordinator (see the module)."""

    def __init__(self, max_attempts: int) -> None:
        super().__init__()
        self.max_attempts = max_attempts
        self.jobs: dict[str, Job] = {}  # in flight
        # the orders of jobs whose subject (a child, an evaluation) has no result yet (a late
        # result is checked against its order); a result forgets them, so the state grows by
        # results, not by jobs
        self.orders: dict[str, TrainJob | EvalJob] = {}
        self.orders_of: dict[str | EvalKey, list[str]] = {}  # subject -> its jobs
        self.by_node: dict[str, str] = {}  # node -> its job in flight
        self.planned: dict[EvalKey, None] = {}  # evaluations of the plan, in order
        self.eval_waiting: deque[EvalKey] = deque()
        self.eval_failures: dict[EvalKey, int] = {}  # failed jobs of each evaluation
        self.eval_given_up: set[EvalKey] = set()  # failed `max_attempts` times

    def known(self, msg: MessageBase) -> bool:
        """Whether the replay applies `msg` (a state that can tell a message lost its context
        with a damaged journal segment says no, with a warning)."""
        return True

    # --- the fold ----------------------------------------------------------------------------

    @handles(EvalJob)
    def on_eval_job(self, msg: EvalJob) -> None:
        super().on_eval_job(msg)
        key = (msg.agent, msg.task, msg.seed, msg.steps)
        self._plan_evaluations()
        if key in self.eval_waiting:
            self.eval_waiting.remove(key)
        self._ordered(key, Job(msg.job, msg.agent, msg.node, msg, key[1:]))

    @handles(EvalResult)
    def on_eval_result(self, msg: EvalResult) -> None:
        super().on_eval_result(msg)
        self._forget_orders((msg.agent, msg.task, msg.seed, msg.steps))
        self._remove(msg.job)
        self._plan_evaluations()

    @handles(Cancel)
    def on_cancel(self, msg: Cancel) -> None:
        self._remove(msg.job)

    @handles(JobLost)
    def on_job_lost(self, msg: JobLost) -> None:
        super().on_job_lost(msg)
        self._take_back(msg.job)

    @handles(JobFailed)
    def on_job_failed(self, msg: JobFailed) -> None:
        super().on_job_failed(msg)
        job = self.jobs.get(msg.job)
        if job is not None and job.evaluation is not None and not msg.unfit:
            key = (job.agent, *job.evaluation)
            self.eval_failures[key] = self.eval_failures.get(key, 0) + 1
            if self.eval_failures[key] >= self.max_attempts:
                self.eval_given_up.add(key)
        self._take_back(msg.job)

    def _ordered(self, subject: str | EvalKey, job: Job) -> None:
        """`job` (for `subject`: a child, or an evaluation) is in flight."""
        self.orders[job.id] = job.order
        self.orders_of.setdefault(subject, []).append(job.id)
        self.jobs[job.id] = job
        self.by_node[job.node] = job.id

    def _forget_orders(self, subject: str | EvalKey) -> None:
        """`subject` (a child or an evaluation) has its result: forget the orders of its jobs."""
        for job_id in self.orders_of.pop(subject, ()):
            self.orders.pop(job_id, None)

    def _remove(self, job_id: str) -> Job | None:
        """`job_id` is no longer in flight: the job, if it was."""
        job = self.jobs.pop(job_id, None)
        if job is not None and self.by_node.get(job.node) == job_id:
            del self.by_node[job.node]
        return job

    def _take_back(self, job_id: str) -> Job | None:
        """A job ends without its result: an evaluation waits for the next ready evaluator (a
        state that trains puts its child back: it extends this). The job, if it was in flight."""
        job = self._remove(job_id)
        if job is not None and job.evaluation is not None:
            key = (job.agent, *job.evaluation)
            if key not in self.evaluations and key not in self.eval_given_up:
                self.eval_waiting.appendleft(key)
        return job

    # --- questions the node asks -------------------------------------------------------------

    def job_of(self, node: str) -> Job | None:
        job = self.by_node.get(node)
        return None if job is None else self.jobs[job]

    def queued(self, role: str) -> bool:
        """Whether work of `role` waits that one worker may not be given and another may (its
        idle workers are all asked, not only the first)."""
        return False

    # --- the evaluation stage ----------------------------------------------------------------

    @abstractmethod
    def _plan_evaluations(self) -> None:
        """Plan what is to be evaluated once it is known (`_plan` each evaluation)."""

    @abstractmethod
    def evaluation_order(self, key: EvalKey) -> tuple[Genome, PPOConfig]:
        """The body and the learning configuration of a planned evaluation."""

    @property
    @abstractmethod
    def eval_target(self) -> int:
        """The evaluations the plan will hold."""

    @property
    @abstractmethod
    def finished(self) -> bool:
        """Whether everything is done: the coordinator writes its results and stops."""

    def _plan(self, key: EvalKey) -> None:
        if key not in self.planned:
            self.planned[key] = None
            if key not in self.evaluations and key not in self.eval_given_up:
                self.eval_waiting.append(key)

    def next_evaluation(self) -> EvalKey | None:
        self._plan_evaluations()
        return self.eval_waiting[0] if self.eval_waiting else None

    @property
    def evaluated(self) -> int:
        return sum(key in self.evaluations for key in self.planned)

    def evaluations_over(self, keys: Iterable[EvalKey]) -> bool:
        """Whether each of `keys` has its result or was given up."""
        return all(key in self.evaluations or key in self.eval_given_up for key in keys)
