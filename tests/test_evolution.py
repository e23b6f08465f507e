"""Aging tournament evolution without a bus: decisions, breeding, births, and their replay."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from derl.analysis.study import load_study_profile
from derl.evolution import Child, Evolution, breed, load_profile
from derl.evolution.evolution import tournament_draws
from derl.unimal import Genome, canonical_genome, check_body, sample_population
from derl.unimal.mutations import OPERATORS


@pytest.fixture(scope="module")
def initial() -> list[Genome]:
    return sample_population(4, np.random.default_rng(3))


def _evolution(initial: list[Genome], in_flight: int = 0) -> Evolution:
    """Free-running by default (its tournaments draw from every birth so far)."""
    config = load_profile("smoke").model_copy(
        update={"population": 4, "tournament": 3, "in_flight": in_flight}
    )
    return Evolution(config, initial)


def test_breeding_is_one_valid_mutation_and_the_same_for_a_seed(initial: list[Genome]) -> None:
    parent = initial[0]
    children = {}
    for seed in range(12):
        child, mutation = breed(parent, seed)
        assert mutation.op in OPERATORS and child != parent
        check_body(child)  # raises if the body is impossible
        assert breed(parent, seed) == (child, mutation)  # wherever it runs
        children[seed] = child
    assert len({c.model_dump_json() for c in children.values()}) > 6


def test_a_child_is_bred_once_where_its_tournament_is_held(initial: list[Genome]) -> None:
    """The holder of the state breeds each tournament child (with the full validity check) the
    first time its body is asked for; a body recorded as a fact (the child's job) is kept and
    never bred again, so a resumed coordinator gives the child the body its job carried."""
    evolution = _evolution(initial)
    for k, child in enumerate(evolution.initial):
        assert evolution.body(child.name) == (canonical_genome(initial[k]), None)
        evolution.birth(child.name, float(k), initial[k])
    decided = evolution.tournament()
    evolution.record(decided)
    body, mutation = evolution.body(decided.name)
    parent = canonical_genome(initial[int(decided.parent[1:])])
    assert (body, mutation) == breed(parent, decided.mutation_seed)
    check_body(body)  # bred with the full validity check: it passes it
    assert evolution.body(decided.name) == (body, mutation)
    other = _evolution(initial)
    for k, child in enumerate(other.initial):
        other.birth(child.name, float(k), initial[k])
    other.record(decided)
    recorded = breed(initial[0], 99)
    other.decided(decided.name, *recorded)  # as its journaled job says
    assert other.body(decided.name) == recorded != (body, mutation)


def test_a_child_whose_body_is_born_is_known_as_a_repeat(initial: list[Genome]) -> None:
    evolution = _evolution(initial)
    for k, child in enumerate(evolution.initial):
        evolution.birth(child.name, float(k), initial[k])
    decided = evolution.tournament()
    evolution.record(decided)
    body, _ = evolution.body(decided.name)
    assert evolution.repeat(decided.name) is None  # its body is new
    shuffled = body.model_copy(update={"limbs": body.limbs[::-1]})  # same body, other order
    assert evolution.repeat_of(shuffled) is None
    evolution.birth(decided.name, 7.0, body)
    assert evolution.repeat_of(shuffled) == decided.name
    again = evolution.tournament()
    evolution.record(replace(again, parent=decided.parent, mutation_seed=decided.mutation_seed))
    evolution.body(again.name)
    assert evolution.repeat(again.name) == decided.name
    twin = evolution.tournament()  # a child bred by hand as the shuffled body: the same body
    evolution.record(twin)
    evolution.decided(twin.name, shuffled, None)
    assert evolution.repeat(twin.name) == decided.name


def test_tournaments_pick_the_fittest_and_children_are_born_with_their_bred_body(
    initial: list[Genome],
) -> None:
    evolution = _evolution(initial)
    assert evolution.tournament() is None  # no agent born to draw from
    for k, child in enumerate(evolution.initial):
        assert evolution.birth(child.name, float(k), initial[k]) is not None
    assert evolution.birth("i0000", 99.0, initial[0]) is None  # born already
    assert evolution.birth("c77777", 1.0, initial[0]) is None  # never decided

    decided = evolution.tournament()
    assert decided == evolution.tournament()  # a decision depends on the state only
    assert decided.genome is None and decided.mutation_seed is not None
    assert (
        decided.parent
        == max(zip(decided.contestants, decided.fitness, strict=True), key=lambda c: c[1])[0]
    )
    evolution.record(decided)
    assert evolution.tournament().name != decided.name  # the next decision
    parent_body = evolution.genomes[decided.parent]
    child_body, _ = evolution.body(decided.name)
    assert child_body == breed(parent_body, decided.mutation_seed)[0]
    member = evolution.birth(decided.name, 50.0, child_body)
    assert member is not None and member.parent == decided.parent
    assert [m.agent for m in evolution.population] == ["i0001", "i0002", "i0003", decided.name]
    assert evolution.best() == member  # the fittest born, aged out of the population or not
    again = evolution.tournament()
    evolution.record(again)
    evolution.birth(again.name, 50.0, evolution.body(again.name)[0])
    assert evolution.best() == member  # the first born of equals


def test_tournament_draws_are_uniform_with_replacement_and_fixed_for_a_seed() -> None:
    assert tournament_draws(1, 0, 4, 64) == ([9, 58, 54, 37], 3066514885187968334)  # any numpy
    assert tournament_draws(1, 0, 4, 64) != tournament_draws(2, 0, 4, 64)
    assert tournament_draws(1, 0, 4, 64) != tournament_draws(1, 1, 4, 64)
    positions, seed = tournament_draws(5, 9, 40, 3)  # more draws than one hash block, and repeats
    assert len(positions) == 40 and set(positions) == {0, 1, 2} and 0 <= seed < 2**63
    counts = np.bincount(
        [p for k in range(4000) for p in tournament_draws(7, k, 4, 8)[0]], minlength=8
    )
    assert counts.sum() == 16000 and np.all(np.abs(counts - 2000) < 200)  # 4.7 sigma


def test_replaying_decisions_and_births_rebuilds_the_state(initial: list[Genome]) -> None:
    live, replayed = _evolution(initial), _evolution(initial)
    facts: list[tuple[Child | None, str, float, Genome]] = []
    for k, child in enumerate(live.initial):
        live.birth(child.name, float(k), initial[k])
        facts.append((None, child.name, float(k), initial[k]))
    for k in range(6):
        decided = live.tournament()
        live.record(decided)
        body = live.body(decided.name)[0]
        live.birth(decided.name, 10.0 + k, body)
        facts.append((decided, decided.name, 10.0 + k, body))
    for decided, agent, fitness, body in facts:
        if decided is not None:
            replayed.record(decided)
            replayed.record(decided)  # a fact recorded twice is one fact
        replayed.birth(agent, fitness, body)
    assert replayed.born == live.born and replayed.genomes == live.genomes
    assert replayed.tournament() == live.tournament()


def test_a_decided_child_waits_for_a_worker_until_its_job_is_journaled(
    initial: list[Genome],
) -> None:
    """A coordinator that died between journaling a Tournament and its TrainJob: the replayed
    fold keeps the child waiting (it is trained next), never decides past it."""
    from derl.messages import Birth, TrainJob
    from derl.messages.examples import examples
    from derl.nodes.coordinator.run.state import EvolutionState, tournament_message
    from derl.rl import PPOConfig

    config = load_profile("smoke").model_copy(update={"population": 4, "tournament": 3})
    state = EvolutionState.start(config, initial)
    template = next(m for m in examples("r") if isinstance(m, Birth))
    ppo = PPOConfig(total_steps=4096, seed=0)
    for k, child in enumerate(state.evolution.initial):
        job = TrainJob(
            run="r",
            job=f"{child.name}.1",
            agent=child.name,
            node="t0",
            genome=child.genome,
            task="ft",
            ppo=ppo,
            lease_s=10.0,
        )
        state.apply(job)
        state.apply(
            template.model_copy(
                update={
                    "agent": child.name,
                    "parent": None,
                    "job": job.job,
                    "node": "t0",
                    "birth": k,
                    "generation": 0,
                    "genome": child.genome,
                    "mutation": None,
                    "fitness": k,
                }
            )
        )
    assert state.wants_tournament()
    decided = state.evolution.tournament()
    tournament = tournament_message("r", decided)
    state.apply(tournament)
    state.apply(tournament)  # replayed twice: still one waiting child
    assert list(state.waiting) == [decided.name] and state.next_child_for("t0", 1) == decided.name
    genome, mutation = state.evolution.body(decided.name)
    state.apply(
        TrainJob(
            run="r",
            job=f"{decided.name}.1",
            agent=decided.name,
            node="t1",
            genome=genome,
            task="ft",
            ppo=ppo,
            parent=decided.parent,
            mutation=mutation.op,
            lease_s=10.0,
        )
    )
    assert not state.waiting and state.job_of("t1").agent == decided.name


def test_replicates_differ_by_their_seed_alone() -> None:
    """`derl run --seed N`: two runs of one profile start from different initial populations
    and hold different tournaments; one seed gives the same run."""

    def start(seed: int) -> tuple[list[Genome], tuple]:
        evolution = Evolution(load_profile("smoke", seed=seed))
        for k, child in enumerate(evolution.initial):
            evolution.birth(child.name, float(k), child.genome)
        decided = evolution.tournament()
        return [c.genome for c in evolution.initial], (decided.contestants, decided.mutation_seed)

    assert load_profile("smoke", seed=7).seed == 7 and load_profile("smoke").seed == 0
    one, two = start(1), start(2)
    assert one == start(1)
    assert all(a != b for a, b in zip(one[0], two[0], strict=True))
    assert one[1] != two[1]


def test_changes_set_dotted_keys_of_a_profile_and_are_checked_like_it(tmp_path: Path) -> None:
    """`--set KEY=VALUE`: a value at a dotted key of a built-in profile or a profile file, read
    as the file's YAML is (so `1e-4` is a string pydantic reads as a number), validated with
    the rest; the world and seed flags still win."""
    config = load_profile("smoke", [("ppo.lr", "1e-4"), ("total", 6), ("world", "vt")], seed=2)
    assert (config.ppo.lr, config.total, config.world, config.seed) == (1e-4, 6, "vt", 2)
    assert config.ppo.gamma == load_profile("smoke").ppo.gamma  # the rest of ppo is kept
    file = tmp_path / "mine.yaml"
    file.write_text("profile: smoke\ntotal: 10\n")
    assert load_profile(str(file), [("total", 5)]).total == 5
    assert load_study_profile("smoke", [("seeds", 3)]).seeds == 3
    with pytest.raises(ValidationError, match=r"ppo\.lrr"):
        load_profile("smoke", [("ppo.lrr", 1)])
    with pytest.raises(ValidationError, match=r"tournament \(20\) > population \(4\)"):
        load_profile("smoke", [("tournament", 20)])
    with pytest.raises(ValueError, match=r"cannot set world\.x: world is one value"):
        load_profile("smoke", [("world.x", 1)])
