"""The coordinator's state: the journal's fold (`RunHistory`) plus the work in flight.

Its handlers extend `RunHistory`'s, and are the only way the state changes, both live and when a
restarted coordinator replays its journal: a Tournament decides a child (`derl.evolution` holds
the rule), a TrainJob or EvalJob puts a job in flight, a Birth makes a child born, a JobLost or a
JobFailed takes a job back (its subject waits for the next worker), a Cancel ends a job whose
child was born from another, a ChildFailed gives a child up, an EvalResult completes an
evaluation; a Birth with `repeat_of` is a child never trained (its body is an earlier one's).
An audited child's FitnessReport is one of its trials (`audits`: it waits for another identity's
until they agree); a Quarantine puts the liar's unchecked births first in the queue, and their
Retrained replaces the result they were born with. Which jobs are in flight, who holds them and
what waits for a worker are all derived here; time (leases) and the checks of incoming messages
are the node's business. A TrainJob also records its child's body (the coordinator bred it: a
fact, so a resumed coordinator trains the same body).
Not from the journal: the children held back because a child with their body is in training
(`hold`); each goes back to the front of the queue once that child is born (then it is born as
its repeat) or given up (a restart forgets them: they are in the queue again, and held again when
they come up).

A journal whose damaged segment was replaced by its repaired part (`derl log repair`) may have
lost a Tournament whose child's job, report or birth are in a later segment: each such message,
and every tournament that drew an agent the journal never saw born, is skipped with a warning
(`known`, asked by the replay), so the run resumes without them instead of failing on a child it
never decided.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from derl.evolution import Child, Evolution, EvolutionConfig, Member
from derl.messages import (
    Birth,
    Cancel,
    ChildFailed,
    EvalJob,
    EvalResult,
    FitnessReport,
    JobFailed,
    JobLost,
    MessageBase,
    Quarantine,
    Retrained,
    Tournament,
    TrainJob,
)
from derl.messages.dispatch import handles
from derl.nodes.coordinator.audits import audited, identity, trials
from derl.nodes.journal.history import EvalKey, RunHistory
from derl.rl import PPOConfig
from derl.unimal import Genome, Mutation

log = logging.getLogger("derl.coordinator")


def tournament_message(run: str, decided: Child) -> Tournament:
    """A decided tournament (`Evolution.tournament`) as the fact the coordinator journals;
    `on_tournament` turns it back into the `Child` it records."""
    return Tournament(
        run=run,
        child=decided.name,
        contestants=decided.contestants,
        fitness=decided.fitness,
        parent=decided.parent,
        mutation_seed=decided.mutation_seed,
        iteration=decided.iteration,
    )


@dataclass
class Job:
    """An assignment in flight."""

    id: str
    subject: str  # the child (training) or agent (evaluation)
    node: str
    order: TrainJob | EvalJob  # as sent (sent again to a worker that missed it)
    evaluation: tuple[str, int, int] | None = None  # (task, seed, steps) for an evaluation


class CoordinatorState(RunHistory):
    def __init__(self, config: EvolutionConfig, evolution: Evolution) -> None:
        super().__init__()
        self.config = config
        self.evolution = evolution
        self.jobs: dict[str, Job] = {}  # in flight
        # the orders of jobs whose subject has no result yet (a late report is checked against
        # its order); a result forgets them, so the state grows by births, not by jobs
        self.orders: dict[str, TrainJob | EvalJob] = {}
        self.orders_of: dict[str | EvalKey, list[str]] = {}  # child or evaluation -> its jobs
        self.attempts: dict[str, int] = {}  # child -> trainings started
        self.failed_on: dict[str, set[str]] = {}  # child -> nodes whose training of it failed
        self.waiting: deque[str] = deque()  # children to (re)assign, in order
        self.planned: dict[EvalKey, None] = {}  # evaluations of the plan, in order
        self.eval_waiting: deque[EvalKey] = deque()
        self.eval_failures: dict[EvalKey, int] = {}  # failed jobs of each evaluation
        self.eval_given_up: set[EvalKey] = set()  # failed `max_attempts` times
        self.by_node: dict[str, str] = {}  # node -> its job in flight
        self.by_child: dict[str, str] = {}  # child -> its training job in flight
        self.in_training: dict[str, str] = {}  # body_hash -> the child in training with it
        self.held: dict[str, str] = {}  # child -> the child in training with its body
        self.holding: dict[str, list[str]] = {}  # that child in training -> the children held
        # audits (`audits`): an audited child's reports until its birth, the identities caught
        # lying, and the born children of theirs to train again
        self.trials: dict[str, list[FitnessReport]] = {}
        self.quarantined: dict[str, Quarantine] = {}
        self.retraining: dict[str, None] = {}
        self.checked: set[str] = set()  # children born from trials that agreed

    @classmethod
    def start(cls, config: EvolutionConfig, initial: list[Genome] | None) -> CoordinatorState:
        state = cls(config, Evolution(config, initial))
        state.waiting.extend(child.name for child in state.evolution.initial)
        return state

    # --- the fold ----------------------------------------------------------------------------

    def known(self, msg: MessageBase) -> bool:
        """Whether `msg` is about a child the journal decided (else logged: it is skipped)."""
        evolution = self.evolution
        if isinstance(msg, Tournament):
            if msg.parent in evolution.genomes:
                return True
            evolution.skip(msg.iteration)
            what = f"Tournament of {msg.child}: its parent {msg.parent} was never born"
        elif isinstance(msg, TrainJob | FitnessReport | Birth | ChildFailed):
            if msg.child in evolution.parents:
                return True
            what = f"{msg.type} of {msg.child}: no tournament decided it"
        else:
            return True
        log.warning("journal: %s (lost with a damaged segment?): skipped", what)
        return False

    @handles(Tournament)
    def on_tournament(self, msg: Tournament) -> None:
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

    @handles(TrainJob)
    def on_train_job(self, msg: TrainJob) -> None:
        super().on_train_job(msg)
        self.orders[msg.job] = msg
        child = msg.child
        self.orders_of.setdefault(child, []).append(msg.job)
        made = None if msg.mutation is None else Mutation(msg.mutation, msg.mutation_detail)
        self.evolution.decided(child, msg.genome, made)
        if child in self.by_child:
            self._remove(self.by_child[child])  # a reassignment supersedes the lost job
        if child in self.waiting:
            self.waiting.remove(child)
        self.attempts[child] = self.attempts.get(child, 0) + 1
        self._add(Job(msg.job, child, msg.node, msg))

    @handles(EvalJob)
    def on_eval_job(self, msg: EvalJob) -> None:
        super().on_eval_job(msg)
        self.orders[msg.job] = msg
        key = (msg.agent, msg.task, msg.seed, msg.steps)
        self.orders_of.setdefault(key, []).append(msg.job)
        self._plan_evaluations()
        if key in self.eval_waiting:
            self.eval_waiting.remove(key)
        self._add(Job(msg.job, msg.agent, msg.node, msg, key[1:]))

    @handles(FitnessReport)
    def on_fitness_report(self, msg: FitnessReport) -> None:
        """An audited child's report is one of its trials: its job is done and, until the trials
        decide (its Birth follows in the same group when they do), the child waits for a
        training by another identity. Nothing else is kept: the coordinator needs no learning
        curve (the journal holds them for `derl report`), and keeping each report's was most of
        its memory's growth per birth."""
        if not self.is_audited(msg.child) or msg.child in self.evolution.fitness:
            return
        self.trials.setdefault(msg.child, []).append(msg)
        self._remove(msg.job)
        if msg.child not in self.by_child and msg.child not in self.waiting:
            self.waiting.appendleft(msg.child)

    @handles(Birth)
    def on_birth(self, msg: Birth) -> None:
        super().on_birth(msg)
        if len(trials(self.trials.pop(msg.child, []))) > 1:
            self.checked.add(msg.child)
        self._forget_orders(msg.child)
        self.evolution.birth(msg.child, msg.fitness, msg.genome, msg.repeat_of)
        self._remove(msg.job)
        if msg.child in self.waiting:  # born from a late report while it waited
            self.waiting.remove(msg.child)
        self._release(msg.child)

    @handles(Cancel)
    def on_cancel(self, msg: Cancel) -> None:
        self._remove(msg.job)

    @handles(Quarantine)
    def on_quarantine(self, msg: Quarantine) -> None:
        """`msg.node` lied: its trials of children not born yet no longer count, and its
        unchecked births wait first in the queue to be trained again."""
        super().on_quarantine(msg)
        self.quarantined[msg.node] = msg
        for reports in self.trials.values():
            reports[:] = [r for r in reports if identity(r.node) != msg.node]
        for child in reversed(msg.retrain):
            if child not in self.retraining:
                self.retraining[child] = None
                self.waiting.appendleft(child)

    @handles(Retrained)
    def on_retrained(self, msg: Retrained) -> None:
        super().on_retrained(msg)
        self.retraining.pop(msg.child, None)
        self.evolution.correct(msg.child, msg.fitness)
        self._forget_orders(msg.child)
        self._remove(msg.job)

    @handles(JobLost)
    def on_job_lost(self, msg: JobLost) -> None:
        super().on_job_lost(msg)
        self._take_back(msg.job)

    @handles(JobFailed)
    def on_job_failed(self, msg: JobFailed) -> None:
        super().on_job_failed(msg)
        self.failed_on.setdefault(msg.subject, set()).add(msg.node)
        job = self.jobs.get(msg.job)
        if job is not None and job.evaluation is not None:
            key = (job.subject, *job.evaluation)
            self.eval_failures[key] = self.eval_failures.get(key, 0) + 1
            if self.eval_failures[key] >= self.config.max_attempts:
                self.eval_given_up.add(key)
        self._take_back(msg.job)

    @handles(ChildFailed)
    def on_child_failed(self, msg: ChildFailed) -> None:
        super().on_child_failed(msg)
        self._forget_orders(msg.child)
        self.evolution.give_up(msg.child)
        if msg.child in self.waiting:
            self.waiting.remove(msg.child)
        self._release(msg.child)

    @handles(EvalResult)
    def on_eval_result(self, msg: EvalResult) -> None:
        super().on_eval_result(msg)
        self._forget_orders((msg.agent, msg.task, msg.seed, msg.steps))
        self._remove(msg.job)
        self._plan_evaluations()

    def _forget_orders(self, subject: str | EvalKey) -> None:
        """`subject` (a child or an evaluation) has its result: forget the orders of its jobs."""
        for job_id in self.orders_of.pop(subject, ()):
            self.orders.pop(job_id, None)

    def _take_back(self, job_id: str) -> None:
        """A job ends without its result: its subject waits for the next ready worker."""
        job = self._remove(job_id)
        if job is None:
            return
        if job.evaluation is None:
            unborn = job.subject not in self.evolution.fitness and job.subject not in self.failed
            if unborn or job.subject in self.retraining:
                self.waiting.appendleft(job.subject)
        else:
            key = (job.subject, *job.evaluation)
            if key not in self.evaluations and key not in self.eval_given_up:
                self.eval_waiting.appendleft(key)

    def training(self, child: str) -> None:
        """`child` (its body decided) is assigned for training: a later child with its body is
        held."""
        self.in_training.setdefault(self.evolution.body_key(child), child)

    def hold(self, child: str) -> bool:
        """Hold `child` (its body decided) back (True) if a child with its body is in training:
        once that one is born, `child` is born as its repeat."""
        earlier = self.in_training.get(self.evolution.body_key(child))
        if earlier is None or earlier == child:
            return False
        if child in self.waiting:
            self.waiting.remove(child)
        self.held[child] = earlier
        self.holding.setdefault(earlier, []).append(child)
        return True

    def _release(self, child: str) -> None:
        """`child` is born or given up: the children held for it go first in the queue."""
        key = self.evolution.hashes.get(child)
        if key is not None and self.in_training.get(key) == child:
            del self.in_training[key]
        for held in reversed(self.holding.pop(child, [])):
            del self.held[held]
            self.waiting.appendleft(held)

    def _add(self, job: Job) -> None:
        self.jobs[job.id] = job
        self.by_node[job.node] = job.id
        if job.evaluation is None:
            self.by_child[job.subject] = job.id

    def _remove(self, job_id: str) -> Job | None:
        job = self.jobs.pop(job_id, None)
        if job is not None:
            if self.by_node.get(job.node) == job_id:
                del self.by_node[job.node]
            if self.by_child.get(job.subject) == job_id:
                del self.by_child[job.subject]
        return job

    # --- questions the node asks -------------------------------------------------------------

    def job_of(self, node: str) -> Job | None:
        job = self.by_node.get(node)
        return None if job is None else self.jobs[job]

    def training_in_flight(self) -> int:
        return len(self.by_child)

    def next_child_for(self, node: str, trainers_alive: int) -> str | None:
        """The first waiting child for `node`: one whose training failed on another node, or on
        this one only if no other trainer is alive to try it; an audited one that another
        identity trained (`tried_by`)."""
        me = identity(node)
        for child in self.waiting:
            if me in self.tried_by(child):
                continue
            if node not in self.failed_on.get(child, ()) or trainers_alive <= 1:
                return child
        return None

    def is_audited(self, child: str) -> bool:
        """Whether `child` is born only once two identities' trainings agree (`audits`)."""
        return audited(self.config.seed, child, self.config.audit)

    def tried_by(self, child: str) -> set[str]:
        """The identities whose training of `child` counts in its audit (or, for a child to
        train again, that lied about it)."""
        if child in self.retraining:
            return {identity(self.born[child].node)}
        return {identity(r.node) for r in trials(self.trials.get(child, []))}

    def wants_tournament(self) -> bool:
        """Whether a new child may be decided for an idle trainer now: once no child waits
        for it (every initial body is assigned: those still training are born when they
        finish), while fewer than the run's total are started (`Evolution.tournament` says
        whether its population is known yet)."""
        evolution = self.evolution
        unborn = [c for c in (*self.by_child, *self.waiting) if c not in self.retraining]
        started = evolution.settled + len(unborn) + len(self.held)
        return started < self.config.total

    def next_job_id(self, child: str) -> str:
        return f"{child}.{self.attempts.get(child, 0) + 1}"

    def failed_trainings(self, child: str) -> int:
        return len(self.failures.get(child, ()))

    # --- evaluation stage --------------------------------------------------------------------

    def _plan_evaluations(self) -> None:
        """Once evolution is over (and no child waits to be trained again): the best `eval_top`
        bodies on every test task and seed."""
        if self.planned or not self.evolution.complete or self.retraining:
            return
        for member in self.best()[: self.config.eval_top]:
            for task in self.config.eval_tasks:
                for seed in range(self.config.eval_seeds):
                    self._plan((member.agent, task, seed, self.config.eval_steps))

    def _plan(self, key: EvalKey) -> None:
        if key not in self.planned:
            self.planned[key] = None
            if key not in self.evaluations and key not in self.eval_given_up:
                self.eval_waiting.append(key)

    def evaluation_order(self, key: EvalKey) -> tuple[Genome, PPOConfig]:
        """The body and the learning configuration of a planned evaluation."""
        agent, task, seed, _ = key
        return self.evolution.genomes[agent], self.config.evaluation_ppo(task, seed)

    def best(self) -> list[Member]:
        """The born bodies, fittest first, each once (a repeat is its earlier agent's body)."""
        evolution = self.evolution
        trained = (m for m in evolution.born if m.repeat_of is None)
        return sorted(trained, key=lambda m: (-m.fitness, evolution.index[m.agent]))

    def next_evaluation(self) -> EvalKey | None:
        self._plan_evaluations()
        return self.eval_waiting[0] if self.eval_waiting else None

    @property
    def evaluated(self) -> int:
        return sum(key in self.evaluations for key in self.planned)

    def evaluations_over(self, keys: Iterable[EvalKey]) -> bool:
        """Whether each of `keys` has its result or was given up."""
        return all(key in self.evaluations or key in self.eval_given_up for key in keys)

    @property
    def eval_target(self) -> int:
        top = min(self.config.eval_top, self.config.total)
        return top * len(self.config.eval_tasks) * self.config.eval_seeds

    @property
    def finished(self) -> bool:
        """Evolution and the evaluations of the run are over."""
        self._plan_evaluations()
        over = self.evolution.complete and not self.retraining
        return over and self.evaluations_over(self.planned)
