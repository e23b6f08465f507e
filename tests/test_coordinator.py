"""The coordinator's handlers on a real Zenoh session: group commit (nothing is published before
the journal file holds it) and checkpoint files (an Ack only once the file is on disk, and a
lost file written again from the repeated report), and a child whose body is born already born
as its repeat, untrained, through a restart (and one bred like a child in training held until
that child is born)."""

from __future__ import annotations

import gc
import json
import logging
import queue
import shutil
import threading
import time
import tracemalloc
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np
import pytest

from derl.evolution import Evolution, EvolutionConfig, breed, evolution, load_profile
from derl.messages import (
    Ack,
    Birth,
    ChildFailed,
    Curve,
    EvalJob,
    FitnessReport,
    JobFailed,
    JobLost,
    MessageBase,
    Reject,
    Rejection,
    Tournament,
    TrainJob,
    TrainProgress,
    WorkerReady,
    decode,
    encode,
)
from derl.nodes.coordinator.ledger import JOURNALED_REFUSALS
from derl.nodes.coordinator.node import RESEND_AFTER_S, Coordinator
from derl.nodes.coordinator.run.audits import journaled
from derl.nodes.coordinator.run.files import INITIAL_FILE, PROFILE_FILE
from derl.nodes.coordinator.run.rules import EvolutionRules
from derl.nodes.coordinator.run.state import EvolutionState
from derl.nodes.errors import Refused
from derl.nodes.journal.history import run_log
from derl.nodes.journal.segments import read_segment
from derl.nodes.runtime.bus import Bus, ZenohOptions, matched, open_session
from derl.nodes.testing.trainers import untrained_policy
from derl.nodes.testing.waiting import ManualClock, wait_until
from derl.rl import PPOConfig, PPOHyperparameters
from derl.unimal import Genome, Joint, Limb, body_hash, sample_population
from tests.nodes_fixtures import free_port, run_id

QUIET_S = 0.5  # how long "nothing was published" is watched for


@contextmanager
def _serving(
    run: str,
    run_dir: Path,
    config: EvolutionConfig,
    initial: list[Genome],
    clock: Callable[[], float] = time.monotonic,
) -> Iterator[tuple[Coordinator, queue.Queue[MessageBase]]]:
    """A coordinator of a run of `initial` bodies on `clock` whose bus is a real Zenoh session,
    and a queue of what an observer in another session hears it publish."""
    (run_dir / INITIAL_FILE).write_text("[" + ",".join(g.model_dump_json() for g in initial) + "]")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    heard: queue.Queue[MessageBase] = queue.Queue()
    with (
        open_session(ZenohOptions(listen=(endpoint,))) as own,
        open_session(ZenohOptions(connect=(endpoint,))) as observer,
    ):
        subscriber = observer.declare_subscriber(
            f"derl/{run}/**", lambda sample: heard.put(decode(sample.payload.to_bytes()))
        )
        policy = EvolutionRules(run, run_dir, config)
        coordinator = Coordinator(run, run_dir, policy, Bus(own, run), clock)
        try:
            yield coordinator, heard
        finally:
            subscriber.undeclare()
            coordinator.close()


@pytest.fixture
def coordinator(tmp_path: Path) -> Iterator[tuple[Coordinator, queue.Queue[MessageBase]]]:
    """The coordinator of a 2-body run of 3 children, on a clock the test moves (`ManualClock`)."""
    config = load_profile("smoke").model_copy(update={"population": 2, "in_flight": 1, "total": 3})
    initial = sample_population(2, np.random.default_rng(3))
    with _serving(run_id(), tmp_path, config, initial, ManualClock()) as served:
        yield served


@pytest.fixture
def coordinator_of(tmp_path: Path) -> Iterator[Callable[..., Coordinator]]:
    """Makes the coordinator of a run of the smoke profile changed by its keywords (`initial`:
    the initial bodies, else drawn), with no evaluation and a real Zenoh session as its bus."""
    with ExitStack() as stack:

        def make(initial: list[Genome] | None = None, **changes: object) -> Coordinator:
            config = load_profile("smoke").model_copy(
                update={"eval_top": 0, "eval_tasks": (), "in_flight": 1, **changes}
            )
            bodies = initial or sample_population(config.population, np.random.default_rng(3))
            served = _serving(run_id(), tmp_path, config, bodies)
            return stack.enter_context(served)[0]

        yield make


def _quiet(heard: queue.Queue[MessageBase]) -> bool:
    try:
        heard.get(timeout=QUIET_S)
    except queue.Empty:
        return True
    return False


def _journaled(coordinator: Coordinator) -> list[MessageBase]:
    return list(read_segment(coordinator.ledger.journal.segment))


def _ready(coordinator: Coordinator, node: str) -> None:
    """`node` asks for work, its liveliness token up (a worker without one gets none)."""
    if node not in coordinator.tokens:
        coordinator._liveliness("trainer", node, True)
    coordinator._ready(WorkerReady(run=coordinator.run, node=node, role="trainer", host="h", pid=1))


def _job_for(coordinator: Coordinator, node: str) -> TrainJob:
    _ready(coordinator, node)
    coordinator.settle()
    job = coordinator.state.job_of(node)
    assert job is not None and isinstance(job.order, TrainJob)
    return job.order


def _weights(job: TrainJob, seed: int) -> bytes:
    return untrained_policy(job.genome, job.task, seed)


def _report(job: TrainJob, checkpoint: bytes | int) -> FitnessReport:
    """`job`'s report; `checkpoint`: its bytes, or the seed of a policy of its body."""
    if isinstance(checkpoint, int):
        checkpoint = _weights(job, checkpoint)
    return FitnessReport(
        run=job.run, agent=job.agent, job=job.job, node=job.node, genome=job.genome,
        fitness=1.0, fitness_source="window", fitness_episodes=1,
        curve=Curve(env_steps=(1, 2), returns=(0.0, 1.0)), energy=1.0, cost_of_work=1.0,
        mass=1.0, episodes=1, env_steps=2, wall_s=0.0, steps_per_s=0.0, checkpoint=checkpoint,
    )  # fmt: skip


def test_a_job_is_published_only_once_the_journal_file_holds_it(
    coordinator: tuple[Coordinator, queue.Queue[MessageBase]],
) -> None:
    node, (coordinator, heard) = "w1", coordinator
    _ready(coordinator, node)
    assert not [m for m in _journaled(coordinator) if isinstance(m, TrainJob)]
    assert _quiet(heard), "a job went out before the journal file had it"

    coordinator.settle()
    sent = heard.get(timeout=10)
    assert isinstance(sent, TrainJob) and sent.node == node
    assert sent in _journaled(coordinator)


def test_an_ack_waits_for_its_checkpoint_and_a_lost_one_is_written_again(
    coordinator: tuple[Coordinator, queue.Queue[MessageBase]],
    caplog: pytest.LogCaptureFixture,
) -> None:
    coordinator, heard = coordinator
    first, second = _job_for(coordinator, "w1"), _job_for(coordinator, "w2")
    assert isinstance(heard.get(timeout=10), TrainJob)
    assert isinstance(heard.get(timeout=10), TrainJob)

    # accepted: the Ack comes, and the checkpoint file is whole by then
    coordinator.dispatch(_report(first, 1))
    coordinator.settle()
    assert isinstance(heard.get(timeout=10), Birth)  # the birth stream: journaled, published
    ack = heard.get(timeout=10)
    assert isinstance(ack, Ack) and ack.agent == first.agent
    assert coordinator.ledger.checkpoints.path(first.agent).read_bytes() == _weights(first, 1)

    # the write fails (the folder is gone, a file in its place): born, but neither published
    # nor acknowledged
    folder = coordinator.ledger.checkpoints.folder
    shutil.rmtree(folder)
    folder.write_text("not a folder")
    report = _report(second, 2)
    with caplog.at_level(logging.ERROR, logger="derl.coordinator"):
        coordinator.dispatch(report)
        coordinator.settle()
    assert second.agent in coordinator.state.evolution.fitness
    assert journaled(report) in _journaled(coordinator)  # its checkpoint: the SHA-256
    assert _quiet(heard), "a Birth or an Ack went out for a checkpoint that is not on disk"
    assert f"cannot write {folder / second.agent}.pt (Not a directory)" in caplog.text
    assert coordinator.ledger.stalled

    # the trainer sends its report again: the checkpoint is written, then the Birth goes out
    # and the report is acknowledged
    folder.unlink()
    folder.mkdir()
    coordinator.dispatch(report)
    coordinator.settle()
    assert isinstance(heard.get(timeout=10), Birth)
    ack = heard.get(timeout=10)
    assert isinstance(ack, Ack) and ack.agent == second.agent
    assert coordinator.ledger.checkpoints.path(second.agent).read_bytes() == _weights(second, 2)
    assert coordinator.rules.born == 2
    assert not coordinator.ledger.stalled


def test_a_restarted_coordinator_names_a_born_childs_missing_file_and_takes_it_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A birth journaled whose file never reached the disk (its writer ended first): the
    restarted coordinator says which file is missing and whose report it waits for, and the
    trainer's report sent again writes it (a Ctrl-C'd `derl run` lost it, and its resume waited
    for the file without a word)."""
    run = run_id()
    config = load_profile("smoke").model_copy(update={"population": 2, "in_flight": 1, "total": 3})
    initial = sample_population(2, np.random.default_rng(3))
    with _serving(run, tmp_path, config, initial) as (coordinator, _):
        job = _job_for(coordinator, "w1")
        coordinator.dispatch(_report(job, 1))
        coordinator.settle()
        checkpoint = coordinator.ledger.checkpoints.path(job.agent)
        _written(checkpoint)
    checkpoint.unlink()
    with (
        caplog.at_level(logging.WARNING, logger="derl.coordinator"),
        _serving(run, tmp_path, config, initial) as (restarted, _),
    ):
        assert (f"{job.agent} was born, but its checkpoint file is missing: it waits for w1's "
                f"report of job {job.job}") in caplog.text  # fmt: skip
        restarted.dispatch(_report(job, 1))
        restarted.settle()
        assert _written(checkpoint) == _weights(job, 1)


def _written(path: Path) -> bytes:
    wait_until(path.exists, 10, f"{path} written")
    return path.read_bytes()


def test_a_child_whose_body_is_born_already_is_born_as_its_repeat_untrained(
    tmp_path: Path,
) -> None:
    """Tournament 0's child is made the body of the other founder: it is born at once with that
    founder's result and checkpoint, the trainer gets the next child, and a restarted coordinator
    knows it (and links its checkpoint again if the link was lost)."""
    run = run_id()
    config = load_profile("smoke").model_copy(update={"population": 2, "in_flight": 1, "total": 4})
    evolution = Evolution(config, [Genome(head_density=500, limb_density=500)] * 2)
    for founder in evolution.initial:
        evolution.birth(founder.name, 1.0, founder.genome)
    decided = evolution.tournament()  # its parent and seed do not depend on the bodies
    body = sample_population(1, np.random.default_rng(0))[0]
    child_body = breed(body, decided.mutation_seed)[0]
    initial = [body, child_body] if decided.parent == "i0000" else [child_body, body]
    twin = "i0001" if decided.parent == "i0000" else "i0000"

    with _serving(run, tmp_path, config, initial) as (coordinator, heard):
        for node, weights in (("w1", 1), ("w2", 2)):
            coordinator.dispatch(_report(_job_for(coordinator, node), weights))
        _ready(coordinator, "w1")
        coordinator.settle()
        journaled = _journaled(coordinator)
        births = {m.agent: m for m in journaled if isinstance(m, Birth)}
        repeat = births["c00000"]
        assert repeat.repeat_of == twin and repeat.parent == decided.parent
        assert (repeat.fitness, repeat.job, repeat.generation) == (1.0, births[twin].job, 1)
        assert repeat.genome == child_body and repeat.mutation is not None
        trained = {m.agent for m in journaled if isinstance(m, TrainJob)}
        assert "c00000" not in trained and "c00001" in trained  # the worker got the next one
        assert coordinator.state.job_of("w1").agent == "c00001"
        while not (isinstance(msg := heard.get(timeout=10), Birth) and msg.agent == "c00000"):
            pass
        assert msg.repeat_of == twin  # in the birth stream
        assert coordinator.status().repeats == 1
        checkpoint = coordinator.ledger.checkpoints.path("c00000")
        assert _written(checkpoint) == coordinator.ledger.checkpoints.path(twin).read_bytes()

    checkpoint.unlink()  # as if the coordinator died before the link was on disk
    restarted = Coordinator(run, tmp_path, EvolutionRules(run, tmp_path, config))
    try:
        state = restarted.state
        assert state.born["c00000"].repeat_of == twin
        assert state.evolution.repeat_of(child_body) == twin
        assert "c00000" not in state.waiting and restarted.status().repeats == 1
        assert _written(checkpoint) == restarted.ledger.checkpoints.path(twin).read_bytes()
    finally:
        restarted.close()
    bodies = {body.id: body for body in run_log(tmp_path).bodies}  # what `derl report` reads
    assert bodies["c00000"].repeat_of == twin and bodies[twin].repeat_of is None
    assert bodies["c00000"].curve_returns == bodies[twin].curve_returns == (0.0, 1.0)


def test_the_state_grows_by_births_not_by_jobs_or_learning_curves(tmp_path: Path) -> None:
    """A long run's coordinator keeps no report's learning curve (the journal holds them) and no
    order of a job whose child is born: its memory grows by a few kB a birth (the bodies and
    births it must keep), whatever the length of the curves (a 5M-step training reports about
    1,200 points): 6.9 kB a birth measured, 94 kB before."""
    config = load_profile("smoke").model_copy(
        update={"population": 4, "tournament": 2, "total": 1_000, "eval_top": 0}
    )
    initial = sample_population(4, np.random.default_rng(3))
    with _serving(run_id(), tmp_path, config, initial) as (coordinator, heard):
        _grows_by_births(coordinator, heard)


def _grows_by_births(coordinator: Coordinator, heard: queue.Queue[MessageBase]) -> None:
    curve = Curve(env_steps=tuple(range(1, 1201)), returns=tuple(float(k) for k in range(1200)))
    jobs = {node: _job_for(coordinator, node) for node in ("w1", "w2")}
    turns = deque(jobs)  # the nodes holding a job, the oldest job first

    def births(count: int) -> None:
        for _ in range(count):
            node = turns.popleft()
            report = _report(jobs.pop(node), 0).model_copy(update={"curve": curve})
            coordinator.dispatch(decode(encode(report)))  # as it comes off the bus
            for idle in ("w1", "w2"):  # a child held behind its twin in training may hold
                if idle not in jobs:  # the next tournament back: that worker waits
                    _ready(coordinator, idle)
                    coordinator.settle()
                    job = coordinator.state.job_of(idle)
                    if job is not None:
                        jobs[idle] = job.order
                        turns.append(idle)
            while not heard.empty():  # what this test's observer heard is not the coordinator's
                heard.get()

    births(30)
    gc.collect()
    tracemalloc.start()
    try:
        births(100)
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    assert grown / 100 < 12_000, f"{grown / 100:.0f} bytes a birth"
    state = coordinator.state
    assert not state.reports
    assert set(state.orders) <= {job.job for job in jobs.values()}


def _born(run: str, child: str, parent: str | None, genome: Genome, birth: int) -> Birth:
    return Birth(
        run=run, agent=child, parent=parent, job=f"{child}.1", node="w1", birth=birth,
        generation=int(parent is not None), fitness=1.0, cost_of_work=1.0, energy=1.0, mass=1.0,
        mutation=None if parent is None else "gear", genome=genome,
    )  # fmt: skip


def test_a_child_bred_like_one_in_training_waits_for_its_birth() -> None:
    """Two tournaments that draw the same parent and mutation: the second child is held while
    the first trains, goes first in the queue once it is born, and is then its repeat."""
    config = load_profile("smoke").model_copy(update={"population": 2, "in_flight": 1, "total": 6})
    initial = sample_population(2, np.random.default_rng(3))
    state = EvolutionState.start(config, initial)
    run = "held"
    for k, genome in enumerate(initial):
        state.apply(_born(run, f"i000{k}", None, genome, k))
    seed = 7
    for k in range(2):
        state.apply(Tournament(run=run, agent=f"c0000{k}", contestants=("i0000",),
                               fitness=(1.0,), parent="i0000", mutation_seed=seed,
                               iteration=k))  # fmt: skip
        state.evolution.body(f"c0000{k}")  # bred by the coordinator
    state.training("c00000")
    assert not state.hold("c00000")  # not held for itself
    assert state.hold("c00001") and state.held == {"c00001": "c00000"}
    assert list(state.waiting) == ["c00000"] and state.next_child_for("t0", 2) == "c00000"
    body, _ = breed(initial[0], seed)
    state.apply(_born(run, "c00000", "i0000", body, 2))
    assert list(state.waiting) == ["c00001"] and not state.held and not state.in_training
    assert state.evolution.repeat("c00001") == "c00000"


def test_tournaments_start_once_every_initial_body_is_assigned(
    coordinator_of: Callable[..., Coordinator],
) -> None:
    """Issue 31, as the released code: with 2 trainers and P = 4, a trainer that is free once
    every initial body is assigned gets a tournament child drawn from the births so far, while
    the last initial body still trains; that one is born when it finishes, in birth order, and
    enters the population."""
    coordinator = coordinator_of(population=4, total=8, tournament=2)
    jobs = {w: _job_for(coordinator, w) for w in ("w1", "w2")}  # i0000, i0001
    for worker in ("w1", "w2", "w1"):  # i0000, i0001, i0002 born; i0003 is given to w2
        coordinator.dispatch(_report(jobs[worker], 0))
        jobs[worker] = _job_for(coordinator, worker)
    child = jobs["w1"].agent
    assert child.startswith("c") and jobs["w2"].agent == "i0003"
    tournaments = {m.agent: m for m in _journaled(coordinator) if isinstance(m, Tournament)}
    assert all("i0003" not in t.contestants for t in tournaments.values())  # not born yet
    assert jobs["w1"].parent == tournaments[child].parent and jobs["w1"].mutation is not None
    for worker in ("w2", "w1"):  # the initial body is born first, then the child
        coordinator.dispatch(_report(jobs[worker], 0))
    coordinator.settle()
    births = [m for m in _journaled(coordinator) if isinstance(m, Birth)]
    births = [m.agent for m in births]
    assert births[:3] == ["i0000", "i0001", "i0002"] and births[-2:] == ["i0003", child]
    assert "i0003" in [m.agent for m in coordinator.rules.state.evolution.population]


def test_a_child_no_valid_body_can_be_bred_from_is_given_up_at_once(
    coordinator_of: Callable[..., Coordinator], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The coordinator breeds each child: a parent of which no valid child can be bred (not a
    valid body itself: three limbs in one place, which no single mutation fixes) gives a child
    that is given up at once (ChildFailed, no training: breeding is deterministic, so no retry
    would change it), and the run goes on. (Breeding gives up after 5 draws here, not 100.)"""
    monkeypatch.setattr(evolution, "MAX_DRAWS", 5)
    joint = Joint(axis="x", range=(-30, 60), gear=200)
    limb = Limb(id=0, paired=False, length=0.3, theta=0, phi=90, joints=(joint,))
    stacked = [Genome(head_density=700, limb_density=600, limbs=tuple(
        limb.model_copy(update={"id": k, "length": length}) for k in range(3)))
        for length in (0.3, 0.4)]  # fmt: skip
    coordinator = coordinator_of(population=2, total=3, initial=stacked)
    for worker in ("w1", "w2"):
        coordinator.dispatch(_report(_job_for(coordinator, worker), 0))
    _ready(coordinator, "w1")
    coordinator.settle()
    assert coordinator.state.job_of("w1") is None
    failed = [m for m in _journaled(coordinator) if isinstance(m, ChildFailed)]
    assert [(m.agent, m.attempts) for m in failed] == [("c00000", 0)]
    assert failed[0].error.startswith("MutationFailed: ")
    assert not [m for m in _journaled(coordinator) if isinstance(m, TrainJob) and m.parent]
    assert coordinator.state.evolution.complete and coordinator.status().failed == 1


def test_a_journal_that_lost_a_tournament_resumes_without_that_child_and_its_descendants(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A repaired segment (`derl log repair`) kept what came before the damage; a later segment
    still holds the job and the birth of a child whose tournament was lost, and a child of that
    child in training. The replay skips them, says so, and resumes; no name is given twice."""
    config = load_profile("smoke").model_copy(update={"population": 2, "in_flight": 1, "total": 6})
    initial = sample_population(2, np.random.default_rng(3))
    state = EvolutionState.start(config, initial)
    run = "repaired"
    body = breed(initial[0], 7)[0]

    def job(child: str, parent: str, genome: Genome) -> TrainJob:
        return TrainJob(run=run, job=f"{child}.1", agent=child, node="w1", genome=genome,
                        task=config.world, ppo=config.training_ppo(), parent=parent,
                        mutation="gear", lease_s=config.lease_s)  # fmt: skip

    kept = [_born(run, f"i000{k}", None, genome, k) for k, genome in enumerate(initial)]
    later = [  # Tournament(c00000, parent i0000, iteration 0) was in the damaged part
        job("c00000", "i0000", body),
        _born(run, "c00000", "i0000", body, 2),
        Tournament(
            run=run,
            agent="c00001",
            contestants=("c00000",),
            fitness=(1.0,),
            parent="c00000",
            mutation_seed=3,
            iteration=1,
        ),
        job("c00001", "c00000", breed(body, 3)[0]),
    ]
    with caplog.at_level(logging.WARNING, logger="derl.coordinator"):
        for msg in [*kept, *later]:  # as a restarted coordinator replays its journal
            if state.known(msg):
                state.apply(msg)
        for child in state.by_child:  # what a restarted coordinator does next (`start`)
            state.training(child)
        state.evolution.settle_skipped()
    assert set(state.born) == {"i0000", "i0001"} and not state.jobs
    skipped = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(skipped) == 4 and all("c0000" in line for line in skipped), skipped
    assert state.wants_tournament() and state.evolution.tournament().name == "c00002"


def test_an_evaluation_that_keeps_failing_is_given_up_and_the_run_finishes() -> None:
    """An evaluation whose job fails `max_attempts` times (a body the test task cannot load) is
    given up like a child, not handed out forever: the run finishes with the others' results."""
    config = load_profile("smoke").model_copy(
        update={
            "population": 2,
            "in_flight": 1,
            "total": 2,
            "eval_top": 1,
            "eval_tasks": ("patrol",),
        }
    )
    initial = sample_population(2, np.random.default_rng(3))
    state = EvolutionState.start(config, initial)
    run = "evalfail"
    for k, genome in enumerate(initial):
        state.apply(_born(run, f"i000{k}", None, genome, k))
    key = state.next_evaluation()
    assert key is not None and key[3] == config.eval_steps
    agent, task, _, _ = key
    genome, ppo = state.evaluation_order(key)
    for attempt in range(config.max_attempts):
        assert not state.finished and state.next_evaluation() == key
        job = f"e{attempt}"
        state.apply(EvalJob(run=run, job=job, agent=agent, node="w", genome=genome, task=task,
                            ppo=ppo, lease_s=config.lease_s))  # fmt: skip
        state.apply(JobFailed(run=run, job=job, node="w", agent=agent, error="boom"))
    assert state.eval_given_up == {key}
    assert state.next_evaluation() is None and state.finished


def test_a_job_goes_out_again_for_a_worker_that_asks_only_after_a_while(
    coordinator: tuple[Coordinator, queue.Queue[MessageBase]],
) -> None:
    """A WorkerReady sent before the job reached its worker does not send the job again (under a
    backlog those re-sends made a 10,000-worker run collapse); one a while later does (the job
    was lost, or the coordinator restarted)."""
    coordinator, heard = coordinator
    job = _job_for(coordinator, "w1")
    assert heard.get(timeout=10) == job
    coordinator.clock.advance(RESEND_AFTER_S / 2)
    _ready(coordinator, "w1")
    coordinator.settle()
    assert _quiet(heard), "the job was sent again too soon"
    coordinator.clock.advance(RESEND_AFTER_S / 2)
    _ready(coordinator, "w1")
    coordinator.settle()
    assert heard.get(timeout=10) == job


def test_progress_keeps_a_job_and_a_lease_without_it_takes_the_job_back(
    coordinator: tuple[Coordinator, queue.Queue[MessageBase]],
) -> None:
    """On the coordinator's clock, moved by hand: progress within each lease keeps the job; a
    lease without progress takes it back (JobLost, journaled), and the next worker gets it."""
    coordinator, _ = coordinator
    clock = coordinator.clock
    job = _job_for(coordinator, "w1")
    progress = TrainProgress(run=job.run, agent=job.agent, job=job.job, node="w1", env_steps=1,
                             total_steps=job.steps, recent_return=None,
                             steps_per_s=1.0)  # fmt: skip
    for _ in range(3):
        clock.advance(0.9 * job.lease_s)
        coordinator.take(progress)
        coordinator._check_leases(clock())
    assert coordinator.state.job_of("w1") is not None
    clock.advance(job.lease_s + 0.1)
    coordinator._check_leases(clock())
    coordinator.settle()
    assert coordinator.state.job_of("w1") is None
    lost = [m for m in _journaled(coordinator) if isinstance(m, JobLost)]
    assert [(m.job, m.node) for m in lost] == [(job.job, "w1")], lost
    assert f"no progress for {job.lease_s:g} s" in lost[0].reason
    assert _job_for(coordinator, "w2").agent == job.agent


def test_an_ask_that_waited_in_a_backlog_does_not_send_the_job_again(
    coordinator: tuple[Coordinator, queue.Queue[MessageBase]],
) -> None:
    """A WorkerReady handled long after the job went out, but that came in before (it waited in
    the coordinator's queue behind others: its inlet was not seen empty since), does not send
    the job again; one that came in RESEND_AFTER_S after the job went out does. Real Zenoh: the
    asks come into the coordinator's inlet through its session."""
    coordinator, heard = coordinator
    bus, clock = coordinator.bus, coordinator.clock
    coordinator.ready_inlet = inlet = bus.inlet(bus.keys.all("ready"), (WorkerReady,), clock=clock)
    changes: queue.SimpleQueue[tuple[str, str, bool]] = queue.SimpleQueue()
    job = _job_for(coordinator, "w1")
    assert heard.get(timeout=10) == job
    ask = WorkerReady(run=coordinator.run, node="w1", role="trainer", host="h", pid=1)
    bus.publish(ask)  # sent before the job could reach w1 ...
    assert heard.get(timeout=10) == ask  # heard by the observer: in the inlet already
    clock.advance(2 * RESEND_AFTER_S)  # ... and handled long after, as behind a backlog
    assert coordinator._take_group([inlet], changes)
    coordinator.settle()
    assert not _orders_heard(heard), "the job sent again for an ask that came in before it"
    bus.publish(ask)  # the inlet was seen empty RESEND_AFTER_S after the job went out
    assert heard.get(timeout=10) == ask
    assert coordinator._take_group([inlet], changes)
    coordinator.settle()
    assert _orders_heard(heard) == [job]


def _orders_heard(heard: queue.Queue[MessageBase]) -> list[MessageBase]:
    """The job orders heard within QUIET_S (the asks, heard too, left out)."""
    orders = []
    deadline = time.monotonic() + QUIET_S
    while (left := deadline - time.monotonic()) > 0:
        try:
            msg = heard.get(timeout=left)
        except queue.Empty:
            break
        if not isinstance(msg, WorkerReady):
            orders.append(msg)
    return orders


def test_a_worker_that_asked_when_there_was_no_work_gets_a_job_once_there_is_some(
    tmp_path: Path,
) -> None:
    """Three trainers ask once each for a run of two initial bodies: the third gets nothing
    until both are born, then the first tournament's child without asking again (an idle worker
    asks again only after 1, 2, 4, then every 8 s: 10,000 idle workers asking every second
    drowned the coordinator)."""
    run, endpoint = run_id(), f"tcp/127.0.0.1:{free_port()}"
    config = load_profile("smoke").model_copy(update={"population": 2, "in_flight": 1, "total": 3})
    initial = sample_population(2, np.random.default_rng(3))
    (tmp_path / INITIAL_FILE).write_text(json.dumps([g.model_dump() for g in initial]))
    coordinator = Coordinator(run, tmp_path, EvolutionRules(run, tmp_path, config))
    serving = threading.Thread(target=coordinator.serve, args=(ZenohOptions(listen=(endpoint,)),))
    serving.start()
    jobs: queue.Queue[TrainJob] = queue.Queue()
    try:
        with open_session(ZenohOptions(connect=(endpoint,))) as session:
            bus = Bus(session, run)
            bus.subscribe(bus.keys.all("job"), jobs.put, (TrainJob,))
            workers = ("w1", "w2", "w3")
            tokens = [bus.token("trainer", worker) for worker in workers]
            asking = session.declare_publisher(bus.keys.ready("w1"))
            wait_until(lambda: matched(asking) and coordinator.tokens >= set(workers), 10,
                       "the coordinator's subscriptions here, the tokens there")  # fmt: skip
            for worker in ("w1", "w2", "w3"):
                bus.publish(WorkerReady(run=run, node=worker, role="trainer", host="h", pid=1))
            first, second = jobs.get(timeout=10), jobs.get(timeout=10)
            assert {first.node, second.node} == {"w1", "w2"}
            with pytest.raises(queue.Empty):  # no tournament before the initial bodies are born
                jobs.get(timeout=QUIET_S)
            for job in (first, second):
                bus.publish(_report(job, 0))
            third = jobs.get(timeout=10)
            assert (third.node, third.agent) == ("w3", "c00000")
            for token in tokens:
                token.undeclare()
    finally:
        coordinator.stop.set()
        serving.join(timeout=30)
    assert not serving.is_alive()


def test_a_run_saved_when_ppo_held_every_ppoconfig_field_resumes_as_it_ran(tmp_path: Path) -> None:
    """Until 2026-12-03 a run's `profile.json` held every `PPOConfig` field under `ppo`, each
    job's copies, budget and seed included, which no job used (theirs came from the profile's
    own fields, as now): such a run resumes with its saved hyperparameters, and its jobs train
    as they did; in a profile, the same keys are an error (tests/test_cli_errors.py)."""
    config = load_profile("smoke")
    saved = config.model_dump(mode="json")
    saved["ppo"] = PPOConfig(num_envs=64, total_steps=10**7, seed=5, lr=1e-4).model_dump()
    (tmp_path / PROFILE_FILE).write_text(json.dumps(saved))
    initial = sample_population(config.population, np.random.default_rng(3))
    (tmp_path / INITIAL_FILE).write_text(json.dumps([g.model_dump() for g in initial]))
    run = run_id()
    coordinator = Coordinator(run, tmp_path, EvolutionRules(run, tmp_path, config))
    try:
        assert coordinator.rules.config.ppo == PPOHyperparameters(lr=1e-4)
        ppo = coordinator.rules.config.training_ppo()
        assert (ppo.num_envs, ppo.total_steps, ppo.seed, ppo.lr) == (
            config.num_envs, config.train_steps, config.training_seed, 1e-4)  # fmt: skip
    finally:
        coordinator.close()


def test_a_run_directory_of_another_profile_is_refused(tmp_path: Path) -> None:
    """The coordinator raises (the command line prints it and exits, `derl run` stops at once):
    a run directory of another profile is `Refused`, naming both."""
    (tmp_path / PROFILE_FILE).write_text(load_profile("smoke").model_dump_json())
    with pytest.raises(Refused, match="holds a run of profile smoke in ft with seed 0, not demo"):
        EvolutionRules(run_id(), tmp_path, load_profile("demo"))


def test_a_run_whose_jobs_would_not_be_valid_messages_is_refused(tmp_path: Path) -> None:
    """Every value a job carries is checked before anything starts (here the run id, which every
    message and key carries)."""
    with pytest.raises(Refused, match="run 'no spaces' cannot start"):
        EvolutionRules("no spaces", tmp_path, load_profile("smoke"))
    assert not (tmp_path / INITIAL_FILE).exists()


def test_who_comes_before_what_and_copies_of_a_taken_report_leave_the_journal_as_it_was(
    coordinator_of: Callable[..., Coordinator],
) -> None:
    """A report for a job never given to its sender is rejected even when its child is born
    already (it got an Ack before); copies of a taken report are acknowledged again without a
    journal write each (a flood of them grew the journal by an Ack each)."""
    coordinator = coordinator_of(population=2, total=3)
    job = _job_for(coordinator, "w1")
    coordinator.dispatch(decode(encode(_report(job, 0))))
    coordinator.settle()
    assert job.agent in coordinator.state.born
    forged = _report(job, b"forged").model_copy(update={"node": "w2"})
    coordinator.dispatch(decode(encode(forged)))
    coordinator.settle()
    answers = [m for m in _journaled(coordinator) if isinstance(m, Ack | Reject)]
    assert isinstance(answers[-1], Reject) and answers[-1].node == "w2", answers
    assert "never issued to w2" in answers[-1].reason
    before = len(_journaled(coordinator))
    for _ in range(300):
        coordinator.dispatch(decode(encode(_report(job, 0))))
    coordinator.settle()
    assert len(_journaled(coordinator)) == before


def test_a_flood_of_refused_messages_from_one_identity_journals_a_bounded_share(
    coordinator_of: Callable[..., Coordinator],
) -> None:
    """Reports for jobs never given to their sender, from one identity under its restart names,
    as fast as it can: every one is refused, counted and answered (a Reject), but only
    `JOURNALED_REFUSALS` a minute are journaled (each was, so such a flood grew the journal
    without bound); another identity's refusals are journaled as before."""
    coordinator = coordinator_of(population=2, total=3)
    job = _job_for(coordinator, "w1")
    report = _report(job, 0)
    before = len(_journaled(coordinator))
    for k in range(3 * JOURNALED_REFUSALS):
        name = "evil" if k % 3 == 0 else f"evil.r{k % 3}"
        forged = report.model_copy(update={"node": name, "job": f"forged.{k}"})
        coordinator.dispatch(decode(encode(forged)))
    coordinator.dispatch(decode(encode(report.model_copy(update={"node": "other"}))))
    coordinator.settle()
    refusals = [m for m in _journaled(coordinator)[before:] if isinstance(m, Reject)]
    assert [m.node.split(".")[0] for m in refusals] == ["evil"] * JOURNALED_REFUSALS + ["other"]
    assert coordinator.ledger.rejected == 3 * JOURNALED_REFUSALS + 1
    assert coordinator.ledger.unjournaled == 2 * JOURNALED_REFUSALS


def test_a_checkpoint_that_is_not_a_policy_of_its_body_is_never_born(
    coordinator_of: Callable[..., Coordinator],
) -> None:
    """A report whose checkpoint does not load, or is another body's network, is rejected and
    journaled: a 17-byte `FORGED-CHECKPOINT` was born, became the run's best and went to
    `best/`, where nothing could read it."""
    coordinator = coordinator_of(population=2, total=3)
    first, second = _job_for(coordinator, "w1"), _job_for(coordinator, "w2")
    assert body_hash(first.genome) != body_hash(second.genome)
    for job, checkpoint, why in (
        (first, b"FORGED-CHECKPOINT", "does not load"),
        (first, _weights(second, 0), "the body in ft"),
    ):
        coordinator.dispatch(_report(job, checkpoint))
        coordinator.settle()
        rejects = [m for m in _journaled(coordinator) if isinstance(m, Reject)]
        assert why in rejects[-1].reason, rejects[-1].reason
    assert not coordinator.state.born
    assert not coordinator.ledger.checkpoints.path(first.agent).exists()
    coordinator.dispatch(_report(second, 3))
    coordinator.settle()
    assert list(coordinator.state.born) == [second.agent]


def test_one_worker_per_identity_and_none_without_a_liveliness_token(
    coordinator_of: Callable[..., Coordinator],
) -> None:
    """One trainer certificate posed as `<node>.r901`, `.r902` and `.rX-evil` without a token
    and got a job each: a worker gets work only with its liveliness token up, and one identity
    (`<id>` and its restarts `<id>.r<n>`) has one live worker: a later restart ends the earlier
    one's job, an earlier one is refused (journaled once)."""
    coordinator = coordinator_of(population=4, total=8)
    coordinator._ready(WorkerReady(run=coordinator.run, node="t.r901", role="trainer", host="h",
                                   pid=1))  # fmt: skip
    coordinator.settle()
    assert coordinator.state.job_of("t.r901") is None  # no token
    first = _job_for(coordinator, "t")
    later = _job_for(coordinator, "t.r1")  # its restart: the first one's job goes back
    assert coordinator.state.job_of("t") is None and later.agent == first.agent
    for _ in range(3):
        _ready(coordinator, "t")  # the earlier incarnation, back: refused
    coordinator.settle()
    assert coordinator.state.job_of("t") is None
    refused = [m for m in _journaled(coordinator) if isinstance(m, Rejection)]
    assert len(refused) == 1 and "t.r1 is alive" in refused[0].reason
    assert coordinator.status().workers_alive == 1
