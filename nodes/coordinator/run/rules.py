"""A run's rules: the aging tournament evolution as jobs, births and failures.

A ready trainer gets the first waiting child (an initial body, or one whose job was lost or
failed: on another trainer than the one it failed on, while there is one), else, once every
initial body is assigned and one is born, the child of a new tournament drawn from the births so
far (`derl.evolution` holds the rule; the `Tournament` is journaled). The coordinator decides
every body: it breeds a tournament's child itself (`Evolution.body`: `breed` with its full
validity check, a few ms; a child of which no valid body can be bred is given up at once) and
sends the body in the job, which records it. A body born already is not trained again: the child
is born at once as its repeat (Birth `repeat_of`, with its result, and its checkpoint file
linked) and the trainer gets the next child. A child whose body is that of a child in training is
held back until that one is born (`EvolutionState.hold`), then born as its repeat.

The first valid report for a child is its birth, whoever trained it (another job for it is
cancelled): valid when the job was issued to the sender for that child, the body is the job's,
the fitness is within what the world allows and the env steps within the job's budget; its
checkpoint is written, and the Birth and the Ack go out once it is on disk. A report that can
never be taken is rejected. A child whose training failed `max_attempts` times is given up
(ChildFailed). Once evolution is over the best bodies are evaluated (`evaluations`), and the
run's results are written (`files`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import TypeVar

from pydantic import ValidationError

from derl.evolution import EvolutionConfig
from derl.messages import (
    Birth,
    Cancel,
    ChildFailed,
    Dropped,
    EvalJob,
    EvalResult,
    FitnessReport,
    JobFailed,
    JobLost,
    ParentWeights,
    PopulationEntry,
    PopulationSnapshot,
    Quarantine,
    Retrained,
    RunSettings,
    TrainJob,
    Undo,
)
from derl.nodes.coordinator.evaluations import evaluation_job, log_given_up, on_evaluation
from derl.nodes.coordinator.jobs import Job
from derl.nodes.coordinator.ledger import Ledger
from derl.nodes.coordinator.rules import Progress
from derl.nodes.coordinator.run.audits import Verdict, identity, journaled, trials, verdict
from derl.nodes.coordinator.run.files import (
    read_initial_population,
    run_config,
    save_initial_population,
    write_results,
)
from derl.nodes.coordinator.run.state import EvolutionState, tournament_message
from derl.nodes.errors import Refused
from derl.plugins import PluginError
from derl.policy_check import policy_problem
from derl.unimal import Genome, MutationFailed
from derl.unimal.space import DENSITIES

log = logging.getLogger("derl.coordinator")
T = TypeVar("T")


class EvolutionRules:
    """The rules of an evolution run of `config` in `run_dir` (see the module)."""

    def __init__(self, run: str, run_dir: Path, config: EvolutionConfig) -> None:
        self.run, self.run_dir = run, run_dir
        self.config = run_config(run_dir, config)
        check_jobs(run, self.config)
        self.state = EvolutionState.start(self.config, read_initial_population(run_dir))
        evolution = self.state.evolution
        save_initial_population(run_dir, [evolution.genomes[c.name] for c in evolution.initial])
        # the same for every job of the run: built once (each builds the world's task)
        self.training_ppo = self.config.training_ppo()
        self.fitness_bound = self.config.fitness_bound()
        self.plugins = self.config.plugins()
        self.trial_files: dict[str, Future[None]] = {}  # audited child -> its file's last write

    @property
    def born(self) -> int:
        return len(self.state.evolution.born)

    def start(self, ledger: Ledger) -> None:
        """Redo what the journal's replay leaves: holds behind children in training, and the
        checkpoint links of repeats a crash may have lost."""
        self.ledger = ledger
        self.logged_born = self.born
        self.said_window = False  # that more trainers run than children are in flight
        self.state.evolution.settle_skipped()
        for child in self.state.by_child:  # children in training hold later equal ones
            self.state.training(child)
        for birth in self.state.births:
            if ledger.checkpoints.path(birth.agent).exists():
                continue
            if birth.repeat_of is not None:
                ledger.link(birth.agent, birth.repeat_of)
            else:  # journaled, its file not yet written when the coordinator stopped
                log.warning("%s was born, but its checkpoint file is missing: it waits for "
                            "%s's report of job %s, sent again until acknowledged (if that "
                            "trainer stopped too, its file is lost)", birth.agent, birth.node,
                            birth.job)  # fmt: skip
        self._undo()  # if the coordinator stopped before it, once the liars' births were in
        self._released_end()
        settings = self.config.model_dump_json()
        if not self.state.settings or self.state.settings[-1] != settings:
            if self.state.settings:
                log.info("the run goes on with other settings (%s): journaled",
                         ", ".join(changed(self.state.settings[-1], settings)))  # fmt: skip
            ledger.commit(RunSettings(run=self.run, settings=settings), publish=False)

    # --- jobs --------------------------------------------------------------------------------

    def next_job(self, node: str, role: str, trainers: int) -> TrainJob | EvalJob | None:
        if role == "trainer":
            return self._training(node, trainers)
        return evaluation_job(self.state, self.run, node, self.config.lease_s, self.plugins)

    def _training(self, node: str, trainers: int) -> TrainJob | None:
        """The next child to train for `node`; children whose body is born already are born as
        repeats on the way, without training, and children that cannot be bred are given up."""
        state, evolution = self.state, self.state.evolution
        if identity(node) in state.quarantined:
            return None
        if trainers <= 1:
            self._born_unchecked(node)
        self._released_end()
        window = self.config.in_flight
        if 0 < window < trainers and not self.said_window:
            self.said_window = True
            log.warning("%d trainers for %d children in flight (the profile's in_flight): about "
                        "%d of them wait; more trainers want a larger in_flight (a new run: it "
                        "changes the evolution)", trainers, window, trainers - window)  # fmt: skip
        while True:
            child = state.next_child_for(node, trainers)
            if child is None and state.wants_tournament():
                decided = self._plugged(evolution.tournament)
                if decided is None:
                    return None  # its population is not known yet: the trainer waits
                self.ledger.commit(tournament_message(self.run, decided))
                child = decided.name
            if child is None:
                return None
            if (
                self._bred(child)
                and not self._born_as_repeat(child)
                and not self._born_as_kept(child)
                and not state.hold(child)
            ):
                break
        state.training(child)
        genome, mutation = evolution.body(child)
        parent = evolution.parents[child]
        job = TrainJob(
            run=self.run,
            job=state.next_job_id(child),
            agent=child,
            node=node,
            genome=genome,
            task=self.config.world,
            ppo=self.training_ppo,
            parent=parent,
            mutation=None if mutation is None else mutation.op,
            mutation_detail="" if mutation is None else mutation.detail,
            lease_s=self.config.lease_s,
            inherit=None if parent is None or not state.inherits else self._weights(parent),
            plugins=self.plugins,
        )
        log.debug("%s -> %s (%s)", child, node, job.job)
        return job

    def _plugged(self, decide: Callable[[], T]) -> T:
        """`decide()`, where a plugin of the run (a selection scheme, an operator) that fails
        stops the coordinator with the plugin's reason (`Refused`: a restart cannot help)."""
        try:
            return decide()
        except PluginError as error:
            raise Refused(f"run {self.run!r} cannot go on: {error}") from None

    def _weights(self, parent: str) -> ParentWeights:
        """`parent`'s trained controller, as a child that inherits it is told (its file:
        `checkpoints/<parent>.pt`, which the trainer asks for on `checkpoint/<parent>`)."""
        return ParentWeights(
            genome=self.state.evolution.genomes[parent], sha256=self.state.sha256[parent]
        )

    def _born_unchecked(self, node: str) -> None:
        """`node` is the only trainer: an audited child it trained, that no other identity can
        train now, is born from its training unchecked (the run would wait forever); a
        disagreement waits for a third identity whatever the number of trainers."""
        me = identity(node)
        for child in [c for c in self.state.waiting if c in self.state.trials]:
            counted = trials(self.state.trials[child])
            if len(counted) == 1 and identity(counted[0].node) == me:
                log.info("%s born unchecked: no other trainer is alive to audit it", child)
                order = self.state.orders[counted[0].job]
                assert isinstance(order, TrainJob)
                self._birth(counted[0], order, self.trial_files.get(child))

    def _bred(self, child: str) -> bool:
        """Whether `child` has its body (bred now if it is a tournament's new child); a child no
        valid body can be bred from (every drawn operator failed: deterministic, so no retry
        would change it) is given up."""
        try:
            self._plugged(lambda: self.state.evolution.body(child))
        except MutationFailed as failure:
            log.error("%s given up: no valid child of %s can be bred (%s)", child,
                      self.state.evolution.parents[child], failure)  # fmt: skip
            self.ledger.commit(
                ChildFailed(
                    run=self.run,
                    agent=child,
                    parent=self.state.evolution.parents[child],
                    attempts=0,
                    error=f"MutationFailed: {failure}"[:1000],
                )
            )
            return False
        return True

    def _born_as_repeat(self, child: str) -> bool:
        """If `child`'s body is born already (a repeat: training is deterministic within a
        run), it is born now with that body's result and checkpoint, and True."""
        earlier = self.state.evolution.repeat(child)
        if earlier is None:
            return False
        self._born_from(child, self.state.born[earlier], earlier, earlier)
        log.debug("born %s as a repeat of %s", child, earlier)
        return True

    def _born_as_kept(self, child: str) -> bool:
        """If an undone child's honest training had `child`'s body (and parent's training, where
        children inherit: `Evolution.body_key`), `child` is born now from it (its result, and
        its file kept as `checkpoints/<job>.pt`) without training, and True."""
        kept = self.state.kept.get(self.state.evolution.body_key(child))
        if kept is None:
            return False
        self._born_from(child, kept, None, kept.job)
        log.debug("born %s from %s, the training of an undone child with its body", child,
                  kept.job)  # fmt: skip
        return True

    def _born_from(self, child: str, result: Birth, repeat_of: str | None, file: str) -> None:
        """`child` is born with the result of an earlier `Birth` (`repeat_of`: that agent's,
        a repeat), its checkpoint file a link to `file`'s (an agent's, or a kept job's)."""
        state = self.state
        genome, mutation = state.evolution.body(child)
        parent = state.evolution.parents[child]
        birth = result.model_copy(
            update={
                "agent": child,
                "parent": parent,
                "birth": state.next_birth(),
                "generation": state.generation(parent),
                "mutation": None if mutation is None else mutation.op,
                "mutation_detail": "" if mutation is None else mutation.detail,
                "genome": genome,
                "repeat_of": repeat_of,
            }
        )
        self.ledger.commit(birth, after=self.ledger.link(child, file))

    # --- results -----------------------------------------------------------------------------

    def on_fitness(self, report: FitnessReport) -> None:
        state, ledger = self.state, self.ledger
        order = state.orders.get(report.job)
        child = report.agent
        if not state.issued_to(report.job, report.node, child):
            ledger.never_issued(report, child)  # whatever the child's state
        elif identity(report.node) in state.quarantined:
            ledger.reject(report, child, f"{identity(report.node)} is quarantined: it lied")
        elif child in state.dropped:
            ledger.reject(report, child, "the child was dropped at the run's released end (it "
                          "kept the N bodies that finished first)")  # fmt: skip
        elif report.job in state.undone:
            ledger.reject(report, child, f"the child of job {report.job} was undone: its "
                          "tournament is decided again (a lie swayed it)")  # fmt: skip
        elif child in state.born and not (child in state.retraining and order is not None):
            saved = None  # a crash (or a failed write) may have lost its checkpoint file
            born_from = state.born[child].job
            if born_from == report.job and not ledger.checkpoints.path(child).exists():
                saved = ledger.save(child, report.checkpoint)
            ledger.answer_again(report, child, after=saved)
        elif child in state.failed:
            ledger.reject(report, child, "the child was given up")
        elif not isinstance(order, TrainJob):
            ledger.never_issued(report, child)
        elif any(trial.job == report.job for trial in state.trials.get(child, ())):
            ledger.answer_again(report, child)  # a trial taken already
        elif wrong := self._wrong_report(report, order):
            ledger.reject(report, child, wrong)
        else:
            saved = ledger.save(child, report.checkpoint)
            ledger.commit(journaled(report), publish=False)
            if child in state.retraining:
                self._retrained(report, saved)
            elif not state.is_audited(child):
                self._birth(report, order, saved)
            elif decided := verdict(state.trials[child]):
                self._decided(decided, order, saved)
            else:  # a trial: the birth waits for its file too (`_born_unchecked`)
                self.trial_files[child] = saved
            ledger.ack(report, child, after=saved)
            if child in state.born:
                self._end_other_job(child, report.job)

    def _birth(self, report: FitnessReport, order: TrainJob, file: Future[None] | None) -> None:
        """`child` is born from `report` (its trials', if audited); the Birth is published once
        `file` (the child's checkpoint file being written, if it is) is on the disk."""
        state = self.state
        self.trial_files.pop(report.agent, None)
        birth = Birth(
            run=self.run,
            agent=report.agent,
            parent=order.parent,
            job=report.job,
            node=report.node,
            birth=state.next_birth(),
            generation=state.generation(order.parent),
            fitness=report.fitness,
            cost_of_work=report.cost_of_work,
            energy=report.energy,
            mass=report.mass,
            mutation=order.mutation,
            mutation_detail=order.mutation_detail,
            genome=order.genome,
            episodes=report.episodes,
            constraint_rows=report.constraint_rows,
        )
        self.ledger.commit(birth, after=file)
        log.debug("born %s fitness %.2f", report.agent, report.fitness)

    def _end_other_job(self, child: str, done: str) -> None:
        """A report for `child` was taken from job `done`: another job for it is cancelled."""
        if self.state.by_child.get(child) not in (None, done):
            self._cancel(child, f"answered by {done}")

    def _decided(self, decided: Verdict, order: TrainJob, file: Future[None]) -> None:
        """An audit's trials decided: the birth, and the liar's quarantine (`audits`)."""
        state, child = self.state, order.agent
        jobs = tuple(r.job for r in trials(state.trials[child]))
        if decided.undecided:
            log.warning("%s: its trainings %s disagree, none alike: the trainers do not train "
                        "alike (other machines or library versions?); born from %s, nobody "
                        "quarantined", child, ", ".join(jobs), decided.born_from.job)  # fmt: skip
        self._birth(decided.born_from, order, file)
        if decided.liar is None:
            return
        liar = decided.liar
        retrain = tuple(b.agent for b in state.births if b.repeat_of is None
                        and identity(b.node) == liar and b.agent not in state.checked)  # fmt: skip
        log.error("%s lied about %s (trainings %s): quarantined; %d of its births are trained "
                  "again", liar, child, ", ".join(jobs), len(retrain))  # fmt: skip
        self.ledger.commit(
            Quarantine(run=self.run, node=liar, agent=child, jobs=jobs, retrain=retrain)
        )
        for job in list(state.jobs.values()):
            if identity(job.node) == liar:
                self.ledger.commit(JobLost(run=self.run, job=job.id, node=job.node,
                                           reason=f"{liar} is quarantined"))  # fmt: skip

    def _retrained(self, report: FitnessReport, file: Future[None]) -> None:
        """A child born from a liar's report, trained again: its result is this one's (published
        once its new checkpoint `file` is on the disk)."""
        was = self.state.born[report.agent].fitness
        same = ("agent", "job", "node", "fitness", "cost_of_work", "energy", "mass", "episodes",
                "constraint_rows")  # fmt: skip
        result = {k: getattr(report, k) for k in same}
        self.ledger.commit(Retrained(run=self.run, was=was, **result), after=file)
        for birth in self.state.births:  # its repeats' files: links to the new one
            if birth.repeat_of == report.agent:
                self.ledger.link(birth.agent, report.agent)
        log.info("%s trained again: fitness %.2f (it was born with %.2f)", report.agent,
                 report.fitness, was)  # fmt: skip
        self._undo()

    def _released_end(self) -> None:
        """With the released end (`end: released`), once it is known (`Evolution.released_end`):
        the jobs of the children that are not among the N that finished first are cancelled and
        they are dropped (a Dropped, published)."""
        state = self.state
        drop = state.evolution.released_end()
        if drop is None:
            return
        for child in drop:
            self._cancel(child, "the run ended (the released end)")
        clock = state.evolution.clock
        assert clock is not None
        last = state.evolution.by_index[clock.finished[self.config.total - 1][1]].agent
        log.info("the released end: %s was the %d-th body to finish; %d children in flight or "
                 "past it are dropped", last, self.config.total, len(drop))  # fmt: skip
        self.ledger.commit(Dropped(run=self.run, agent=last, agents=tuple(drop)))

    def _cancel(self, child: str, why: str) -> None:
        """Cancel `child`'s job in flight, if it has one (`why`: the reason its trainer is told)."""
        job = self.state.by_child.get(child)
        if job is not None:
            node = self.state.jobs[job].node
            self.ledger.commit(Cancel(run=self.run, job=job, node=node, reason=f"{child}: {why}"))

    def _undo(self) -> None:
        """Undo the caught lies once the liars' births are all trained again
        (`EvolutionState.undo_due`): every tournament decided after the first of those births
        is void. The jobs of their children are cancelled, each born one's checkpoint file is
        kept as `checkpoints/<job>.pt` (a child bred again with its body is born from it), and
        the Undo is committed (published once those files are on the disk); the tournaments
        are then decided again, as the honest run of the seed decided them."""
        state = self.state
        if not state.undo_due:
            return
        iteration = state.undo_from
        assert iteration is not None
        void = state.evolution.decided_from(iteration)
        for child in void:
            self._cancel(child, "undone, a lie swayed its tournament")
        kept = None  # the last file kept: written after the others
        for child in void:
            birth = state.born.get(child)
            if birth is not None and birth.repeat_of is None:
                kept = self.ledger.link(birth.job, child)
        caught = list(state.quarantined.values())[-1]
        voided = sum(child in state.born for child in void)
        log.warning("undoing %s's lie: tournaments c%05d on (%d children, %d born) are decided "
                    "again with the honest results", caught.node, iteration, len(void),
                    voided)  # fmt: skip
        undo = Undo(run=self.run, node=caught.node, agent=caught.agent, iteration=iteration,
                    voided=voided)  # fmt: skip
        self.ledger.commit(undo, after=kept)

    def _wrong_report(self, report: FitnessReport, order: TrainJob) -> str:
        """Why `report` cannot be accepted for `order` ("" if it can): the body is the job's
        (the coordinator decided it), the fitness within the world's bound, the env steps within
        the job's budget, and the checkpoint a policy of the body in the world (`policy_check`):
        a report can misstate only the fitness within its bound."""
        if report.genome != order.genome:
            return "not the body of its job"
        bound = self.fitness_bound
        if not abs(report.fitness) <= bound:
            return f"fitness {report.fitness:g} is beyond what the world allows (|f| <= {bound:g})"
        if report.env_steps > order.steps:
            return f"{report.env_steps} env steps trained, the job allowed {order.steps}"
        return policy_problem(report.checkpoint, order.genome, order.task)

    def on_evaluation(self, result: EvalResult) -> None:
        on_evaluation(self.ledger, result)

    def on_failure(self, failure: JobFailed, job: Job) -> None:
        """An evaluation given up is logged; a child given up after `max_attempts` failed
        trainings is a ChildFailed."""
        state, attempts = self.state, self.config.max_attempts
        log_given_up(state, job, attempts)
        if job.evaluation is None and state.failed_trainings(job.agent) >= attempts:
            log.error("%s given up after %d failed trainings", job.agent, attempts)
            self.ledger.commit(
                ChildFailed(
                    run=self.run,
                    agent=job.agent,
                    parent=state.evolution.parents.get(job.agent),
                    attempts=state.failed_trainings(job.agent),
                    error=failure.error,
                )
            )

    # --- what the run looks like -------------------------------------------------------------

    def progress(self) -> Progress:
        best = self.state.evolution.best()
        return Progress(
            born=self.born,
            target=self.config.total,
            best_fitness=None if best is None else best.fitness,
            best_agent=None if best is None else best.agent,
            audited=len(self.state.checked),
            retraining=len(self.state.retraining),
        )

    def snapshot(self) -> PopulationSnapshot:
        members = tuple(
            PopulationEntry(agent=m.agent, fitness=m.fitness, parent=m.parent, birth=m.birth)
            for m in self.state.evolution.population
        )
        given = self.state.evolution.births_made  # an undone birth's number is not given again
        return PopulationSnapshot(run=self.run, birth_counter=given, members=members)

    def log_progress(self) -> None:
        """One line for the births since the last call (a line per birth would be a thousand a
        second on a large cluster)."""
        new = self.state.evolution.born[self.logged_born :]
        if not new:
            return
        fittest = max(new, key=lambda m: m.fitness)
        also = f" (the fittest of {len(new)} new)" if len(new) > 1 else ""
        log.info("born %d/%d: %s fitness %.2f%s", self.born, self.config.total, fittest.agent,
                 fittest.fitness, also)  # fmt: skip
        self.logged_born = self.born

    def finish(self) -> None:
        write_results(self.run_dir, self.run, self.config, self.state, self.ledger.checkpoints)
        log.info("run %s finished: %d born (fingerprint %s), results in %s", self.run, self.born,
                 self.state.fingerprint(), self.run_dir)  # fmt: skip


def check_jobs(run: str, config: EvolutionConfig) -> None:
    """`Refused` with the reason if a job of this configuration would not be a valid message,
    so every value a job carries is checked before anything starts (with a bare head for its
    body: the configuration is checked, not a body)."""
    head = Genome(head_density=DENSITIES[0], limb_density=DENSITIES[0])
    try:
        ids = {"run": run, "job": "check", "node": "check", "genome": head}
        plugins = config.plugins()
        TrainJob(**ids, agent="check", task=config.world, ppo=config.training_ppo(),
                 lease_s=config.lease_s, plugins=plugins)  # fmt: skip
        for task in config.eval_tasks:
            for seed in range(config.eval_seeds):
                EvalJob(**ids, agent="check", task=task, ppo=config.evaluation_ppo(task, seed),
                        lease_s=config.lease_s, plugins=plugins)  # fmt: skip
    except (ValueError, ValidationError) as error:
        raise Refused(f"run {run!r} cannot start: {error}") from None


def changed(was: str, now: str) -> list[str]:
    """The settings that differ between two profiles as JSON, each as ``key old -> new``."""
    old, new = json.loads(was), json.loads(now)
    return [f"{k} {old.get(k)} -> {new[k]}" for k in new if old.get(k) != new[k]]
