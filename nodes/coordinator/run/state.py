"""A run's state: the job book (`jobs`) plus the evolution, its queue of children and audits.

Its handlers extend the book's, and are the only way the state changes, both live and when a
restarted coordinator replays its journal: a Tournament decides a child (`derl.evolution` holds
the rule), a TrainJob puts its training in flight, a Birth makes a child born, a JobLost or a
JobFailed takes a job back (its child waits for the next trainer), a Cancel ends a job whose
child was born from another, a ChildFailed gives a child up; a Birth with `repeat_of` is a child
never trained (its body is an earlier one's). Once evolution is over the best bodies are
evaluated (the book's evaluation stage). An audited child's FitnessReport is one of its trials
(`audits`: it waits for another identity's until they agree; the child's first report decides
whether it is audited, from the identities' records its births keep); a Quarantine puts the liar's
unchecked births first in the queue, and their Retrained replaces the result they were born
with; once they are all trained again, an Undo makes every tournament decided after the first of
the liar's births void (`on_undo`: their children forgotten, an honest training kept for a body
bred again), so the run goes on as the honest run of its seed. A TrainJob also records its
child's body (the coordinator bred it: a fact, so a resumed coordinator trains the same body).
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
import struct
from collections import deque

from derl.evolution import Child, Evolution, EvolutionConfig, Member
from derl.messages import (
    Birth,
    ChildFailed,
    Dropped,
    FitnessReport,
    JobFailed,
    MessageBase,
    Quarantine,
    Retrained,
    Tournament,
    TrainJob,
    Undo,
)
from derl.messages.dispatch import handles
from derl.nodes.coordinator.jobs import Job, JobBook
from derl.nodes.coordinator.run.audits import Record, Rules, identity, result_bits, trials
from derl.nodes.journal.history import EvalKey
from derl.rl import PPOConfig
from derl.unimal import Genome, Mutation

log = logging.getLogger("derl.coordinator")


def tournament_message(run: str, decided: Child) -> Tournament:
    """A decided tournament (`Evolution.tournament`) as the fact the coordinator journals;
    `on_tournament` turns it back into the `Child` it records."""
    return Tournament(
        run=run,
        agent=decided.name,
        contestants=decided.contestants,
        fitness=decided.fitness,
        parent=decided.parent,
        mutation_seed=decided.mutation_seed,
        iteration=decided.iteration,
    )


class EvolutionState(JobBook):
    """A run's jobs, evolution, queue of children and audits (see the module)."""

    def __init__(self, config: EvolutionConfig, evolution: Evolution) -> None:
        super().__init__(config.max_attempts)
        self.config = config
        self.evolution = evolution
        self.attempts: dict[str, int] = {}  # child -> trainings started (undone ones too: a job
        # id is never given twice)
        self.failed_on: dict[str, set[str]] = {}  # child -> nodes whose training of it failed
        self.waiting: deque[str] = deque()  # children to (re)assign, in order
        self.by_child: dict[str, str] = {}  # child -> its training job in flight
        self.in_training: dict[str, str] = {}  # body_hash -> the child in training with it
        self.held: dict[str, str] = {}  # child -> the child in training with its body
        self.holding: dict[str, list[str]] = {}  # that child in training -> the children held
        # audits (`audits`): an audited child's reports until its birth, the identities caught
        # lying, and the born children of theirs to train again
        self.trials: dict[str, list[FitnessReport]] = {}
        self.retraining: dict[str, None] = {}
        self.checked: set[str] = set()  # children born from trials that agreed
        self.rules = Rules.of(config)
        self.auditing: set[str] = set()  # unborn children its rules audit (at their first report)
        self.records: dict[str, Record] = {}  # identity -> its record
        # where children inherit (`inherit: parent`): the SHA-256 of each report's checkpoint
        # (job -> digest, until its child is born) and of each born agent's file (agent -> it)
        self.inherits = config.inherit == "parent"
        self.report_sha256: dict[str, bytes] = {}
        self.sha256: dict[str, bytes] = {}
        # undoing a caught lie (`on_undo`): the tournaments decided before each birth, the first
        # tournament to decide again once the liars' births are trained again, the honest
        # trainings of undone children (body_key -> the Birth; its job -> its file's SHA-256)
        # and every job of an undone child (a late report of one is refused)
        self.decided_before: dict[str, int] = {}
        self.undo_from: int | None = None
        self.kept: dict[str, Birth] = {}
        self.kept_sha256: dict[str, bytes] = {}
        self.undone: set[str] = set()

    @classmethod
    def start(cls, config: EvolutionConfig, initial: list[Genome] | None) -> EvolutionState:
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
            what = f"Tournament of {msg.agent}: its parent {msg.parent} was never born"
        elif isinstance(msg, TrainJob | FitnessReport | Birth | ChildFailed):
            if msg.agent in evolution.parents:
                return True
            what = f"{msg.type} of {msg.agent}: no tournament decided it"
        else:
            return True
        log.warning("journal: %s (lost with a damaged segment?): skipped", what)
        return False

    @handles(Tournament)
    def on_tournament(self, msg: Tournament) -> None:
        self.evolution.record(
            Child(
                msg.agent,
                None,
                msg.parent,
                msg.contestants,
                msg.fitness,
                msg.mutation_seed,
                msg.iteration,
            )
        )
        if msg.agent not in self.by_child and msg.agent not in self.waiting:
            self.waiting.append(msg.agent)  # until its TrainJob (lost if the node died)

    @handles(TrainJob)
    def on_train_job(self, msg: TrainJob) -> None:
        super().on_train_job(msg)
        child = msg.agent
        made = None if msg.mutation is None else Mutation(msg.mutation, msg.mutation_detail)
        self.evolution.decided(child, msg.genome, made)
        if child in self.by_child:
            self._remove(self.by_child[child])  # a reassignment supersedes the lost job
        if child in self.waiting:
            self.waiting.remove(child)
        self.attempts[child] = self.attempts.get(child, 0) + 1
        self._ordered(child, Job(msg.job, child, msg.node, msg))
        self.by_child[child] = msg.job

    @handles(FitnessReport)
    def on_fitness_report(self, msg: FitnessReport) -> None:
        """A child's first report decides whether it is audited (`Rules.audits`, from its
        identity's record, which every report adds to). An audited child's report is one of its
        trials: its job is done and, until the trials
        decide (its Birth follows in the same group when they do), the child waits for a
        training by another identity. Nothing else is kept: the coordinator needs no learning
        curve (the journal holds them for `derl report`), and keeping each report's was most of
        its memory's growth per birth; where children inherit, the checkpoint's SHA-256 (a
        journaled report's `checkpoint`) until the child is born."""
        if self.inherits:
            self.report_sha256[msg.job] = msg.checkpoint
        if msg.agent in self.evolution.fitness:
            return  # a retraining
        record = self.records.setdefault(identity(msg.node), Record())
        first = msg.agent not in self.trials
        if first and self.rules.audits(
            msg.agent, msg.node, msg.fitness, record, lambda: self.evolution.population
        ):
            self.auditing.add(msg.agent)
        record.reports += 1
        if not self.is_audited(msg.agent):
            return
        self.trials.setdefault(msg.agent, []).append(msg)
        self._remove(msg.job)
        if msg.agent not in self.by_child and msg.agent not in self.waiting:
            self.waiting.appendleft(msg.agent)

    @handles(Birth)
    def on_birth(self, msg: Birth) -> None:
        super().on_birth(msg)
        self._judged(msg, trials(self.trials.pop(msg.agent, [])))
        self.auditing.discard(msg.agent)
        self._forget_orders(msg.agent)
        if self.inherits:
            self._born_sha256(msg.agent, msg.job, msg.repeat_of)
        self.decided_before[msg.agent] = self.evolution.iterations
        work = (msg.episodes, msg.constraint_rows)
        self.evolution.birth(
            msg.agent, msg.fitness, msg.genome, msg.repeat_of, work, msg.cost_of_work
        )
        self._remove(msg.job)
        if msg.agent in self.waiting:  # born from a late report while it waited
            self.waiting.remove(msg.agent)
        self._release(msg.agent)

    @handles(Quarantine)
    def on_quarantine(self, msg: Quarantine) -> None:
        """`msg.node` lied: its trials of children not born yet no longer count, and its unchecked
        births wait first in the queue to be trained again (`on_retrained`)."""
        super().on_quarantine(msg)
        for reports in self.trials.values():
            reports[:] = [r for r in reports if identity(r.node) != msg.node]
        for child in reversed(msg.retrain):
            if child not in self.retraining:
                self.retraining[child] = None
                self.waiting.appendleft(child)

    @handles(Retrained)
    def on_retrained(self, msg: Retrained) -> None:
        """A liar's birth trained again: where the result it was born with was a lie (what
        evolution reads of it differs: fitness, cost of work, the cluster timing's counts, the
        checkpoint children inherit), every tournament decided after its birth is to be
        decided again (`undo_from`) once the liars' births are all trained again."""
        born = self.born.get(msg.agent)
        if born is not None and self._lied(born, msg):
            decided = self.decided_before.get(msg.agent, 0)
            if decided < self.evolution.iterations:
                earlier = self.undo_from
                self.undo_from = decided if earlier is None else min(decided, earlier)
        super().on_retrained(msg)
        self.retraining.pop(msg.agent, None)
        work = None
        if msg.episodes is not None and msg.constraint_rows is not None:
            work = (msg.episodes, msg.constraint_rows)
        self.evolution.correct(msg.agent, msg.fitness, msg.cost_of_work, work)
        if self.inherits:  # its file and its repeats' links are the new training's
            self._born_sha256(msg.agent, msg.job, None)
            for birth in self.births:
                if birth.repeat_of == msg.agent:
                    self._born_sha256(birth.agent, birth.job, msg.agent)
        self._forget_orders(msg.agent)
        self._remove(msg.job)

    def _lied(self, born: Birth, retrained: Retrained) -> bool:
        """Whether `born`'s result differs from its training again in what evolution reads."""
        said = struct.pack("<2d", born.fitness, born.cost_of_work)  # NaN equals NaN
        if said != struct.pack("<2d", retrained.fitness, retrained.cost_of_work):
            return True
        work = (retrained.episodes, retrained.constraint_rows)
        if None not in work and work != (born.episodes, born.constraint_rows):
            return True
        new = self.report_sha256.get(retrained.job)
        return self.inherits and new is not None and self.sha256.get(born.agent) != new

    @handles(Undo)
    def on_undo(self, msg: Undo) -> None:
        """Every tournament from `msg.iteration` on is void: each child's honest training (every
        born one's is, its liar's births trained again) is kept for a body bred again, its jobs
        are refused from now on, and children held behind one of them go back to the queue."""
        evolution = self.evolution
        void = evolution.decided_from(msg.iteration)
        gone = set(void)
        for child in void:
            birth = self.born.get(child)
            if birth is not None and birth.repeat_of is None:
                self.kept[evolution.body_key(child)] = birth
                if child in self.sha256:
                    self.kept_sha256[birth.job] = self.sha256[child]
            if child in self.by_child:
                self._remove(self.by_child[child])
            self._forget_orders(child)
            self._release(child)  # the children held behind it go back to the queue
            self.failed_on.pop(child, None)
            self.trials.pop(child, None)
            self.sha256.pop(child, None)
            self.decided_before.pop(child, None)
            self.auditing.discard(child)
            self.checked.discard(child)
        self._unqueue(gone)
        self.undone.update(job for job, (_, agent) in self.issued.items() if agent in gone)
        super().on_undo(msg)
        evolution.undo(msg.iteration)
        self.undo_from = None

    @handles(Dropped)
    def on_dropped(self, msg: Dropped) -> None:
        """The released end: the dropped children leave the queue, their holds and the
        population (their jobs were cancelled before)."""
        dropped = set(msg.agents)
        for child in msg.agents:
            if child in self.by_child:
                self._remove(self.by_child[child])
            self._forget_orders(child)
        self._unqueue(dropped)
        super().on_dropped(msg)
        self.evolution.drop(list(msg.agents))

    def _unqueue(self, gone: set[str]) -> None:
        """The children `gone` (undone or dropped) leave the queue and the holds."""
        for child in [c for c in self.held if c in gone]:
            self.holding[self.held.pop(child)].remove(child)
        self.waiting = deque(c for c in self.waiting if c not in gone)

    @handles(JobFailed)
    def on_job_failed(self, msg: JobFailed) -> None:
        if not msg.unfit:
            self.failed_on.setdefault(msg.agent, set()).add(msg.node)
        super().on_job_failed(msg)

    @handles(ChildFailed)
    def on_child_failed(self, msg: ChildFailed) -> None:
        super().on_child_failed(msg)
        self.auditing.discard(msg.agent)
        self._forget_orders(msg.agent)
        self.evolution.give_up(msg.agent)
        if msg.agent in self.waiting:
            self.waiting.remove(msg.agent)
        self._release(msg.agent)

    def _judged(self, birth: Birth, counted: list[FitnessReport]) -> None:
        """An audited child is born from its trials `counted`: each identity whose result agreed
        with the one it is born from adds to its record; where none agreed (the trainers do not
        train alike), each of them starts a new record (all its reports audited again)."""
        if len(counted) < 2:
            return
        self.checked.add(birth.agent)
        born = next(r for r in counted if r.job == birth.job)
        agreed = [r for r in counted if r is not born and result_bits(r) == result_bits(born)]
        for report in counted:
            record = self.records.setdefault(identity(report.node), Record())
            if not agreed:
                record.agreed = record.reports = 0
            elif report is born or report in agreed:
                record.agreed += 1

    def _born_sha256(self, agent: str, job: str, repeat_of: str | None) -> None:
        """`agent`'s checkpoint file is the one of `job`'s report, or `repeat_of`'s file."""
        if repeat_of is None:
            digest = self.report_sha256.pop(job, self.kept_sha256.get(job))
        else:
            digest = self.sha256.get(repeat_of)
        if digest is not None:
            self.sha256[agent] = digest

    def _take_back(self, job_id: str) -> Job | None:
        """A job ends without its result: its child (not born, or to train again) waits first in
        the queue for the next ready trainer."""
        job = super()._take_back(job_id)
        if job is not None and job.evaluation is None:
            unborn = job.agent not in self.evolution.fitness and job.agent not in self.failed
            if unborn or job.agent in self.retraining:
                self.waiting.appendleft(job.agent)
        return job

    def _remove(self, job_id: str) -> Job | None:
        job = super()._remove(job_id)
        if job is not None and self.by_child.get(job.agent) == job_id:
            del self.by_child[job.agent]
        return job

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

    # --- questions the node and the rules ask ----------------------------------------------

    def queued(self, role: str) -> bool:
        """A waiting child may be one that an idle trainer may not take and another may."""
        return role == "trainer" and bool(self.waiting)

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
        """Whether `child` is born only once two identities' trainings agree (`audits`: drawn
        from the seed, or asked for by its first report)."""
        return child in self.auditing or self.rules.drawn(child)

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
        if self.retraining or self.undo_from is not None or evolution.closed:
            return False  # a lie may be undone (`on_undo`), or the tournaments are over
        if self.config.end == "released":
            return True  # until N bodies finished by the next breeding (`Evolution.closed`)
        unborn = [c for c in (*self.by_child, *self.waiting) if c not in self.retraining]
        started = evolution.settled + len(unborn) + len(self.held)
        return started < self.config.total

    @property
    def undo_due(self) -> bool:
        """A caught lie is to be undone now: the liars' births are all trained again."""
        return self.undo_from is not None and not self.retraining

    def next_birth(self) -> int:
        """The next Birth's number (an undone birth's is not given again)."""
        return self.births[-1].birth + 1 if self.births else 0

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

    def evaluation_order(self, key: EvalKey) -> tuple[Genome, PPOConfig]:
        agent, task, seed, _ = key
        return self.evolution.genomes[agent], self.config.evaluation_ppo(task, seed)

    def best(self) -> list[Member]:
        """The born bodies, fittest first, each once (a repeat is its earlier agent's body)."""
        evolution = self.evolution
        trained = (m for m in evolution.born if m.repeat_of is None)
        return sorted(trained, key=lambda m: (-m.fitness, evolution.index[m.agent]))

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
