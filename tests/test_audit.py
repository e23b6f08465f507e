"""Audits (`nodes.coordinator.audits`): children trained twice by two identities (a share drawn
from the seed, every report of an identity until one agreed, then a share falling with its
record, and likely parents), a disagreement decided by a third, the liar quarantined and its
unchecked births trained again. The coordinator's own handlers are driven in this process by
simulated trainers whose results depend only on the child (training is deterministic), one of
which adds 1.0 to every fitness."""

from __future__ import annotations

import json
import shutil
import sys
from functools import cache
from pathlib import Path

import pytest
from nodes_fixtures import LocalRun, Processes

from derl.evolution import load_profile
from derl.messages import (
    Birth,
    FitnessReport,
    Quarantine,
    Retrained,
    Tournament,
    TrainJob,
    Undo,
)
from derl.nodes.coordinator.node import Coordinator
from derl.nodes.coordinator.run.audits import audited, journaled, verdict
from derl.nodes.coordinator.run.state import EvolutionState
from derl.nodes.journal.history import load_history
from derl.nodes.journal.segments import JournalWriter, replay
from derl.nodes.testing.trainers import honest, honest_report, simulate_run
from derl.nodes.testing.waiting import wait_until
from derl.unimal import Genome

RUN = "audit"

LIAR = "t3"


SHARE_ALONE = {"audit_first": 0, "audit_top": 0.0}  # the drawn share alone audits
SHARED_RUNS = pytest.mark.xdist_group(name="audit")  # one process builds the runs they compare


def _config(audit: float, **rules: object):
    return load_profile("smoke").model_copy(
        update={
            "population": 6,
            "total": 30,
            "in_flight": 4,
            "audit": audit,
            "eval_top": 0,
            "eval_tasks": (),
            **rules,
        }
    )


def run_with(folder: Path, audit: float, liar: str | None, **rules: object) -> Coordinator:
    """The run to its end (every child born, none waiting to be trained again)."""
    return simulate_run(RUN, folder, _config(audit, **rules), ["t0", "t1", "t2", "t3"], liar)


def test_the_same_children_are_audited_in_every_run_of_a_seed_and_about_the_share() -> None:
    children = [f"c{k:05d}" for k in range(20_000)]
    chosen = [c for c in children if audited(7, c, 0.05)]
    assert chosen == [c for c in children if audited(7, c, 0.05)]
    assert 0.045 < len(chosen) / len(children) < 0.055
    assert not any(audited(7, c, 0.0) for c in children[:1000])
    assert all(audited(7, c, 1.0) for c in children[:1000])


def _trial(node: str, fitness: float, checkpoint: bytes = b"policy") -> FitnessReport:
    job = TrainJob(run=RUN, job=f"c.{node}", agent="c", node=node, genome=_genome(),
                   task="ft", ppo=_config(0).training_ppo(), lease_s=30)  # fmt: skip
    trial = honest_report(job).model_copy(update={"fitness": fitness, "checkpoint": checkpoint})
    return journaled(trial)


@cache
def _genome() -> Genome:
    return EvolutionState.start(_config(0), None).evolution.initial[0].genome


def test_a_verdict_needs_two_identities_alike_and_a_third_decides_a_disagreement() -> None:
    a, b, c = _trial("a", 1.0), _trial("b.r2", 1.0), _trial("c", 2.0)
    assert verdict([a]) is None
    assert verdict([a, _trial("a.r1", 1.0)]) is None  # one identity twice: one trial
    assert verdict([a, b]).born_from is a and verdict([a, b]).liar is None
    assert verdict([a, c]) is None  # a disagreement waits for a third
    assert verdict([a, c, b]).liar == "c" and verdict([a, c, b]).born_from is a
    assert verdict([c, a, b]).liar == "c" and verdict([c, a, b]).born_from is a
    odd = verdict([a, c, _trial("d", 3.0)])
    assert odd.undecided and odd.liar is None and odd.born_from.node == "d"
    other_policy = _trial("b", 1.0, checkpoint=b"another policy")  # the same fitness
    assert verdict([a, other_policy]) is None


@pytest.fixture(scope="module")
def unaudited(tmp_path_factory: pytest.TempPathFactory) -> Coordinator:
    """The run trained honestly, unaudited (made once for the tests that compare with it)."""
    return run_with(tmp_path_factory.mktemp("unaudited") / "run", 0.0, liar=None)


@SHARED_RUNS
@pytest.mark.parametrize("audit", [0.0, 0.3])
def test_honest_trainers_give_the_births_of_an_unaudited_run(
    tmp_path: Path, audit: float, unaudited: Coordinator
) -> None:
    """An audit changes which trainings are done, never a birth: honest trainings agree."""
    coordinator = unaudited if audit == 0 else run_with(tmp_path / "run", audit, liar=None)
    records = coordinator.state.records
    assert audit == 0 or all(records[t].agreed >= 1 for t in ("t0", "t1", "t2", "t3"))
    state = coordinator.state
    assert not state.quarantined
    assert (len(state.checked) > 0) == (audit > 0)
    fitness = {b.agent: b.fitness for b in state.births}
    assert fitness == {child: honest(b.genome) for child, b in state.born.items()}
    assert len(fitness) == _config(audit).total


@SHARED_RUNS
def test_a_new_identity_that_lies_is_caught_at_its_first_report_and_never_born_from(
    tmp_path: Path, unaudited: Coordinator
) -> None:
    """Every report of a new identity is audited: a liar is caught at the first audit it takes
    part in (its own first child's, or one it was sent as the second identity), none of its
    reports is born from, and the run's births and fingerprint are the honest run's."""
    honest_run = unaudited
    coordinator = run_with(tmp_path / "run", 0.05, liar=LIAR)
    state, journal = coordinator.state, list(replay(tmp_path / "run"))
    (caught,) = [m for m in journal if isinstance(m, Quarantine)]
    tried = [m for m in journal if isinstance(m, FitnessReport) and m.node == LIAR]
    assert caught.agent in {m.agent for m in tried[:2]} and caught.retrain == ()
    assert not [b for b in state.births if b.node == LIAR]
    assert state.fingerprint() == honest_run.state.fingerprint()
    assert {b.agent: b.fitness for b in state.births} == {
        b.agent: b.fitness for b in honest_run.state.births
    }


@pytest.fixture(scope="module")
def undone(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Coordinator]:
    """The run with the liar, audited by the drawn share alone (made once): its folder."""
    folder = tmp_path_factory.mktemp("undone") / "run"
    return folder, run_with(folder, 0.3, liar=LIAR, **SHARE_ALONE)


@SHARED_RUNS
def test_a_trainer_that_adds_one_to_every_fitness_is_caught_and_its_lie_undone(
    undone: tuple[Path, Coordinator], unaudited: Coordinator
) -> None:
    """Audited by the drawn share alone, the liar is caught at the first audited child it trains;
    each of its births that no audit checked is trained again, then every tournament decided
    after the first of them is decided again (an Undo), the honest trainings of the children
    undone kept for the bodies bred again: the run ends with the births and the fingerprint of
    the honest run. After the catch the liar gets no job, and a coordinator started on the
    journal knows all of it."""
    folder, coordinator = undone
    state, journal = coordinator.state, list(replay(folder))
    assert list(state.quarantined) == [LIAR]
    (caught,) = [m for m in journal if isinstance(m, Quarantine)]
    tried = [m for m in journal if isinstance(m, FitnessReport) and m.node == LIAR]
    first = next(m.agent for m in tried if state.is_audited(m.agent))
    assert caught.agent == first  # its first audited training
    liar_births = {m.agent for m in journal if isinstance(m, Birth) and m.node == LIAR}
    assert set(caught.retrain) == liar_births and liar_births  # every one trained again
    retrained = {m.agent: m for m in journal if isinstance(m, Retrained)}
    assert set(retrained) == liar_births
    assert all(r.was == r.fitness + 1.0 and r.node != LIAR for r in retrained.values())
    after = journal.index(caught)
    assert not [m for m in journal[after:] if isinstance(m, TrainJob) and m.node == LIAR]
    assert LIAR not in coordinator.idle["trainer"]  # it would stand before the others' turn

    (undo,) = [m for m in journal if isinstance(m, Undo)]
    assert journal.index(undo) > max(journal.index(m) for m in retrained.values())
    assert undo.voided > 0 and undo.node == LIAR
    honest_run = unaudited.state
    assert state.fingerprint() == honest_run.fingerprint()
    assert {b.agent: (b.parent, b.fitness) for b in state.births} == {
        b.agent: (b.parent, b.fitness) for b in honest_run.births
    }
    at = journal.index(undo)
    trained_before = {m.job for m in journal[:at] if isinstance(m, TrainJob)}
    kept = [m for m in journal[at:] if isinstance(m, Birth) and m.job in trained_before]
    assert kept  # bodies bred again born from the undone children's trainings, not trained
    assert all((folder / "checkpoints" / f"{m.agent}.pt").exists() for m in kept)
    truth = {child: honest(b.genome) for child, b in state.born.items()}
    assert {m.agent: m.fitness for m in state.evolution.born} == truth
    assert all(m.fitness == truth[m.agent] for m in state.evolution.population)
    assert state.evolution.best().fitness == max(truth.values())
    history = load_history(folder)  # what `derl report` reads
    assert {b.agent: b.fitness for b in history.births} == truth
    assert history.fingerprint() == honest_run.fingerprint()
    assert list(history.quarantined) == [LIAR]
    summary = json.loads((folder / "summary.json").read_text())
    assert list(summary["quarantined"]) == [LIAR]
    assert all(b["fitness"] == truth[b["agent"]] for b in summary["best"])

    resumed = EvolutionState.start(_config(0.3, **SHARE_ALONE), None)
    for msg in journal:
        resumed.apply(msg)
    assert list(resumed.quarantined) == [LIAR] and not resumed.retraining
    assert resumed.evolution.fitness == state.evolution.fitness
    assert resumed.checked == state.checked
    status = coordinator.status()
    assert status.quarantined == (LIAR,) and status.audited == len(state.checked) > 0


def test_a_lie_undone_in_the_cluster_timing_ends_as_the_honest_run(tmp_path: Path) -> None:
    """In the cluster timing the liar's births' durations join the virtual clock too: a liar
    that lies on half its reports, caught and undone, leaves the honest run's births."""
    config = {"timing": "cluster", "seed": 2}
    names = ["t0", "t1", "t2", "t3"]
    honest_run = simulate_run(RUN, tmp_path / "honest", _config(0.0, **config), names)
    lied = simulate_run(RUN, tmp_path / "lied", _config(0.3, **config, **SHARE_ALONE), names,
                        liar=LIAR, rate=0.5)  # fmt: skip
    assert list(lied.state.quarantined) == [LIAR]
    assert [m for m in replay(tmp_path / "lied") if isinstance(m, Undo)]
    assert lied.state.fingerprint() == honest_run.state.fingerprint()
    # the population it publishes: numbers of undone births are not given again (a real run's
    # coordinator failed on its snapshot: a member's birth index beyond the births it counted)
    snapshot = lied.rules.snapshot()
    assert max(m.birth for m in snapshot.members) < snapshot.birth_counter


@SHARED_RUNS
def test_a_coordinator_stopped_while_it_undoes_a_lie_resumes_the_undoing(
    tmp_path: Path, undone: tuple[Path, Coordinator], unaudited: Coordinator
) -> None:
    """The run of the test above, its coordinator stopped at each step of the undoing (while the
    liar's births are trained again, just before the Undo, just after it, after the first child
    bred again) and started on its journal with honest trainers: each ends as the honest run."""
    lied = undone[0]
    journal = list(replay(lied))
    (caught,) = [m for m in journal if isinstance(m, Quarantine)]
    (undo,) = [m for m in journal if isinstance(m, Undo)]
    at = journal.index(undo)
    redone = next(k for k in range(at, len(journal)) if isinstance(journal[k], Tournament))
    cuts = {
        "retraining": journal.index(caught) + 1,
        "before the undo": at,
        "after the undo": at + 1,
        "after a tournament decided again": redone + 1,
    }
    for name, cut in cuts.items():
        folder = tmp_path / name.replace(" ", "-")
        (folder / "journal").mkdir(parents=True)
        writer = JournalWriter(folder / "journal" / "segment-0000.mcap")
        for msg in journal[:cut]:
            writer.write(msg)
        writer.close()
        shutil.copytree(lied / "checkpoints", folder / "checkpoints")
        resumed = simulate_run(RUN, folder, _config(0.3, **SHARE_ALONE), ["t0", "t1", "t2"])
        assert resumed.state.fingerprint() == unaudited.state.fingerprint(), name
        assert len([m for m in replay(folder) if isinstance(m, Undo)]) == 1, name


def test_a_real_trainer_that_inflates_every_report_leaves_the_honest_run(
    tmp_path: Path, procs: Processes
) -> None:
    """Real nodes: a trainer running derl's own code that reports 1.25 x + 1 of every fitness
    with its real checkpoints (`derl.nodes.testing.liar`), beside two honest trainers, is caught
    at the first audit it takes part in and never born from: the run ends with the births and
    the fingerprint of the same profile and seed trained honestly by two trainers, unaudited."""
    runs = {}
    for name, audit, trainers in (("honest", 0.0, ("a", "b")), ("lied", 0.05, ("a", "b", "x"))):
        (tmp_path / name).mkdir()
        local = LocalRun.at(tmp_path / name, population=4, total=8, in_flight=2, audit=audit)
        for trainer in trainers:
            argv = local.trainer(trainer)
            if trainer == "x":  # the same options, the liar's code
                argv = [sys.executable, "-m", "derl.nodes.testing.liar", *argv[4:]]
            procs.start(f"{name}-{trainer}", argv)
        # the coordinator once every trainer is up: on a fast machine two trainers started
        # first train all 8 bodies before a third one's imports are done
        logs = [f"{name}-{trainer}" for trainer in trainers]
        wait_until(lambda: all("ready for run" in procs.log(log) for log in logs),  # noqa: B023
                   60, "the trainers up")  # fmt: skip
        coordinator = procs.start(f"{name}-coordinator", local.coordinator())
        assert procs.finish(coordinator, timeout=120) == 0, procs.log(f"{name}-coordinator")
        runs[name] = load_history(local.dir)
    honest_run, lied = runs["honest"], runs["lied"]
    assert list(lied.quarantined) == ["x"]
    assert not [b for b in lied.births if b.node == "x"]
    assert [m for m in replay(tmp_path / "lied" / "run") if getattr(m, "node", None) == "x"]
    assert {b.agent: b.fitness for b in lied.births} == {
        b.agent: b.fitness for b in honest_run.births
    }
    assert lied.fingerprint() == honest_run.fingerprint()
