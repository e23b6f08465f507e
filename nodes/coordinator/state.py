"""The coordinator's state as a fold over the messages it journals (event sourcing).

`apply` is the only way the state changes, both live and when a restarted coordinator replays
its journal: a Tournament decides a child (its parent and mutation seed), a TrainJob or EvalJob
assigns a body to a node, a FitnessReport makes a child born with the body its trainer bred, an
EvalResult completes an evaluation. Which jobs are in flight, who holds them
and what waits for a worker are all derived here; time (leases) is the node's business.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from derl.evolution import Child, Evolution, EvolutionConfig
from derl.unimal import Genome
from messages import EvalJob, EvalResult, FitnessReport, MessageBase, Tournament, TrainJob


def tournament_message(run: str, decided: Child) -> Tournament:
    """A decided tournament (`Evolution.tournament`) as the fact the coordinator journals; `apply`
    turns it back into the `Child` it records."""
    return Tournament(
        run=run,
        child=decided.child,
        contestants=decided.contestants,
        fitness=decided.fitness,
        parent=decided.parent,
        mutation_seed=decided.mutation_seed,
        iteration=decided.iteration,
    )


@dataclass
class Job:
    """An assignment in flight."""

    job: str
    subject: str  # the child (training) or agent (evaluation)
    node: str
    order: TrainJob | EvalJob  # as sent (sent again to a worker that missed it)
    evaluation: tuple[str, int] | None = None  # (task, seed) for an evaluation


@dataclass
class CoordinatorState:
    config: EvolutionConfig
    evolution: Evolution
    jobs: dict[str, Job] = field(default_factory=dict)
    attempts: dict[str, int] = field(default_factory=dict)
    waiting: deque[str] = field(default_factory=deque)  # children to (re)assign, in order
    evaluations: dict[tuple[str, str, int], EvalResult | None] = field(default_factory=dict)
    eval_waiting: deque[tuple[str, str, int]] = field(default_factory=deque)
    issued: dict[str, str] = field(default_factory=dict)  # every job ever sent -> its node
    by_node: dict[str, str] = field(default_factory=dict)  # node -> its job in flight
    by_child: dict[str, str] = field(default_factory=dict)  # child -> its training job in flight

    @classmethod
    def start(cls, config: EvolutionConfig, initial: list[Genome] | None) -> CoordinatorState:
        state = cls(config, Evolution(config, initial))
        state.waiting.extend(child.child for child in state.evolution.initial)
        return state

    # --- the fold ----------------------------------------------------------------------------

    def apply(self, msg: MessageBase) -> None:
        if isinstance(msg, Tournament):
            self.evolution.record(
                Child(
                    msg.child,
                    None,
                    msg.parent,
                    msg.contestants,
                    msg.fitness,
                    msg.mutation_seed,
                    msg.iteration,
                )
            )
            if msg.child not in self.by_child and msg.child not in self.waiting:
                self.waiting.append(msg.child)  # until its TrainJob (lost if the node died)
        elif isinstance(msg, TrainJob):
            self.issued[msg.job] = msg.node
            self._assigned(msg)
        elif isinstance(msg, FitnessReport):
            self.evolution.birth(msg.child, msg.fitness, msg.genome)
            self._finished(msg.job)
        elif isinstance(msg, EvalJob):
            self.issued[msg.job] = msg.node
            key = (msg.agent, msg.task, msg.seed)
            self._plan_evaluations()
            if key in self.eval_waiting:
                self.eval_waiting.remove(key)
            self._add(Job(msg.job, msg.agent, msg.node, msg, (msg.task, msg.seed)))
        elif isinstance(msg, EvalResult):
            self.evaluations[(msg.agent, msg.task, msg.seed)] = msg
            self._finished(msg.job)

    def _assigned(self, job: TrainJob) -> None:
        child = job.child
        if child in self.by_child:
            self._remove(self.by_child[child])  # a reassignment supersedes the lost job
        if child in self.waiting:
            self.waiting.remove(child)
        self.attempts[child] = self.attempts.get(child, 0) + 1
        self._add(Job(job.job, child, job.node, job))

    def _finished(self, job: str) -> None:
        self._remove(job)

    def _add(self, job: Job) -> None:
        self.jobs[job.job] = job
        self.by_node[job.node] = job.job
        if job.evaluation is None:
            self.by_child[job.subject] = job.job

    def _remove(self, job_id: str) -> Job | None:
        job = self.jobs.pop(job_id, None)
        if job is not None:
            if self.by_node.get(job.node) == job_id:
                del self.by_node[job.node]
            if self.by_child.get(job.subject) == job_id:
                del self.by_child[job.subject]
        return job

    # --- questions the node asks -------------------------------------------------------------

    def issued_to(self, job: str, node: str) -> bool:
        """Whether `job` was ever given to `node` (a result for any other is forged or lost)."""
        return self.issued.get(job) == node

    def job_of(self, node: str) -> Job | None:
        job = self.by_node.get(node)
        return None if job is None else self.jobs[job]

    def training_in_flight(self) -> int:
        return len(self.by_child)

    def lose(self, job: str) -> None:
        """A job's worker is gone: its body waits for the next ready worker."""
        lost = self._remove(job)
        if lost is None:
            return
        if lost.evaluation is None:
            if lost.subject not in self.evolution.fitness:
                self.waiting.appendleft(lost.subject)
        elif self.evaluations.get((lost.subject, *lost.evaluation)) is None:
            self.eval_waiting.appendleft((lost.subject, *lost.evaluation))

    def wants_tournament(self) -> bool:
        """Whether a new child should be decided for an idle trainer now."""
        evolution = self.evolution
        started = len(evolution.born) + self.training_in_flight() + len(self.waiting)
        return evolution.initial_born and not self.waiting and started < self.config.total

    def next_job_id(self, child: str) -> str:
        return f"{child}.{self.attempts.get(child, 0) + 1}"

    # --- evaluation stage --------------------------------------------------------------------

    def _plan_evaluations(self) -> None:
        """Once every body is born: the best `eval_top` on every test task and seed."""
        if self.evaluations or not self.evolution.done:
            return
        best = sorted(self.evolution.born, key=lambda m: m.fitness, reverse=True)
        for member in best[: self.config.eval_top]:
            for task in self.config.eval_tasks:
                for seed in range(self.config.eval_seeds):
                    key = (member.agent, task, seed)
                    self.evaluations[key] = None
                    self.eval_waiting.append(key)

    def next_evaluation(self) -> tuple[str, str, int] | None:
        self._plan_evaluations()
        return self.eval_waiting[0] if self.eval_waiting else None

    @property
    def evaluated(self) -> int:
        return sum(result is not None for result in self.evaluations.values())

    @property
    def eval_target(self) -> int:
        top = min(self.config.eval_top, self.config.total)
        return top * len(self.config.eval_tasks) * self.config.eval_seeds

    @property
    def finished(self) -> bool:
        return self.evolution.done and self.evaluated >= self.eval_target
