"""Audits (`nodes.coordinator.audits`): a share of the children trained twice by two identities,
a disagreement decided by a third, the liar quarantined and its unchecked births trained again.
The coordinator's own handlers are driven in this process by simulated trainers whose results
depend only on the child (training is deterministic), one of which adds 1.0 to every fitness."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import pytest

from derl.evolution import load_profile
from derl.messages import (
    Ack,
    Birth,
    Cancel,
    FitnessReport,
    MessageBase,
    Quarantine,
    Reject,
    Retrained,
    TrainJob,
    WorkerReady,
    decode,
    encode,
)
from derl.nodes.coordinator.audits import audited, journaled, verdict
from derl.nodes.coordinator.evolution import EvolutionPolicy
from derl.nodes.coordinator.evolution_state import EvolutionState
from derl.nodes.coordinator.node import Coordinator, Liveliness
from derl.nodes.journal.history import load_history
from derl.nodes.journal.segments import replay
from derl.nodes.testing.trainers import Recorder, honest, honest_report
from derl.unimal import Genome

RUN = "audit"

LIAR = "t3"


def _config(audit: float):
    return load_profile("smoke").model_copy(
        update={
            "population": 6,
            "total": 30,
            "in_flight": 4,
            "audit": audit,
            "eval_top": 0,
            "eval_tasks": (),
        }
    )


@dataclass
class Trainers:
    """Simulated trainers: each answers its job at once and, once answered, asks for work once:
    an idle one then waits among the coordinator's idle workers for its next job."""

    names: list[str]
    liar: str | None = None
    jobs: dict[str, TrainJob] = field(default_factory=dict)  # node -> its unanswered job
    asked: set[str] = field(default_factory=set)  # idle nodes that asked

    def answer(self, heard: list[MessageBase]) -> list[MessageBase]:
        out: list[MessageBase] = []
        for msg in heard:
            node = getattr(msg, "node", None)
            if node not in self.names:
                continue
            if isinstance(msg, TrainJob):
                self.jobs[node] = msg
                self.asked.discard(node)
                out.append(honest_report(msg, 1.0 if node == self.liar else 0.0))
            elif isinstance(msg, Ack | Reject | Cancel) and msg.job == self.jobs.get(node, msg).job:
                del self.jobs[node]
        return out

    def asking(self) -> list[MessageBase]:
        new = [n for n in self.names if n not in self.jobs and n not in self.asked]
        self.asked.update(new)
        return [WorkerReady(run=RUN, node=n, role="trainer", host="sim", pid=1) for n in new]


def run_with(folder: Path, audit: float, liar: str | None, rounds: int = 400) -> Coordinator:
    """The run to its end (every child born, none waiting to be trained again)."""
    heard = Recorder()
    policy = EvolutionPolicy(RUN, folder, _config(audit))
    coordinator = Coordinator(RUN, folder, policy, publisher=heard)
    trainers = Trainers(["t0", "t1", "t2", "t3"], liar)
    for node in trainers.names:
        coordinator.take(Liveliness("trainer", node, True))
    try:
        inbox = trainers.asking()
        for _ in range(rounds):
            if coordinator.state.finished:
                coordinator.policy.finish()
                return coordinator
            for msg in inbox:
                coordinator.take(decode(encode(msg)))
            coordinator.assign_idle()
            coordinator.settle()
            inbox = trainers.answer(heard.messages) + trainers.asking()
            heard.messages.clear()
        raise AssertionError(f"the run did not finish: {coordinator.policy.born} born")
    finally:
        coordinator.close()


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


@pytest.mark.parametrize("audit", [0.0, 0.3])
def test_honest_trainers_give_the_births_of_an_unaudited_run(tmp_path: Path, audit: float) -> None:
    """An audit changes which trainings are done, never a birth: honest trainings agree."""
    coordinator = run_with(tmp_path / "run", audit, liar=None)
    state = coordinator.state
    assert not state.quarantined
    assert (len(state.checked) > 0) == (audit > 0)
    fitness = {b.agent: b.fitness for b in state.births}
    assert fitness == {child: honest(b.repeat_of or child)
                       for child, b in state.born.items()}  # fmt: skip
    assert len(fitness) == _config(audit).total


def test_a_trainer_that_adds_one_to_every_fitness_is_caught_and_no_lie_stays(
    tmp_path: Path,
) -> None:
    """The liar is caught at the first audited child it trains; each of its births that no audit
    checked is trained again, so no lie stays in the population, the births or the results;
    after the catch it gets no job, and a coordinator started on the journal knows all of it."""
    folder = tmp_path / "run"
    coordinator = run_with(folder, 0.3, liar=LIAR)
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
    assert all(r.was == honest(c) + 1.0 for c, r in retrained.items())
    assert all(r.fitness == honest(c) and r.node != LIAR for c, r in retrained.items())
    after = journal.index(caught)
    assert not [m for m in journal[after:] if isinstance(m, TrainJob) and m.node == LIAR]
    assert LIAR not in coordinator.idle["trainer"]  # it would stand before the others' turn

    truth = {child: honest(b.repeat_of or child) for child, b in state.born.items()}
    assert {b.agent: b.fitness for b in state.births} == truth
    assert {m.agent: m.fitness for m in state.evolution.born} == truth
    assert all(m.fitness == truth[m.agent] for m in state.evolution.population)
    assert state.evolution.best().fitness == max(truth.values())
    history = load_history(folder)  # what `derl report` reads
    assert {b.agent: b.fitness for b in history.births} == truth
    assert list(history.quarantined) == [LIAR]
    summary = json.loads((folder / "summary.json").read_text())
    assert list(summary["quarantined"]) == [LIAR]
    assert all(b["fitness"] == truth[b["agent"]] for b in summary["best"])

    resumed = EvolutionState.start(_config(0.3), None)
    for msg in journal:
        resumed.apply(msg)
    assert list(resumed.quarantined) == [LIAR] and not resumed.retraining
    assert resumed.evolution.fitness == state.evolution.fitness
    assert resumed.checked == state.checked
    status = coordinator.status()
    assert status.quarantined == (LIAR,) and status.audited == len(state.checked) > 0
