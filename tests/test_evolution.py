"""Aging tournament evolution without a bus: decisions, breeding, births, and their replay."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from derl.analysis.study import load_study_profile
from derl.evolution import Child, Evolution, breed, load_profile, population
from derl.evolution.population import first_draft, tournament_draws
from derl.unimal import Genome, Joint, Limb, body_hash, check_body, is_valid, sample_population
from derl.unimal.mutations import OPERATORS, MutationFailed


@pytest.fixture(scope="module")
def initial() -> list[Genome]:
    return sample_population(4, np.random.default_rng(3))


def _evolution(initial: list[Genome]) -> Evolution:
    config = load_profile("smoke").model_copy(update={"population": 4, "tournament": 3})
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


def test_a_childs_first_draft_is_the_child_when_valid(initial: list[Genome]) -> None:
    """What `Evolution.repeat` rests on: a born body is valid, so a draft equal to one is the
    child itself."""
    parent, same = initial[1], 0
    for seed in range(30):
        drafted, bred = first_draft(parent, seed), breed(parent, seed)
        if is_valid(drafted[0]):
            assert drafted == bred  # the body and its mutation
            same += 1
    assert same > 20


def test_a_child_whose_body_is_born_is_known_as_a_repeat(initial: list[Genome]) -> None:
    evolution = _evolution(initial)
    for k, child in enumerate(evolution.initial):
        evolution.birth(child.name, float(k), initial[k])
    decided = evolution.tournament()
    evolution.record(decided)
    assert evolution.repeat(decided.name) is None  # its body is new
    body, mutation = breed(*evolution.to_train(decided.name))
    shuffled = body.model_copy(update={"limbs": body.limbs[::-1]})  # same body, other order
    evolution.birth(decided.name, 7.0, shuffled)
    again = evolution.tournament()
    evolution.record(replace(again, parent=decided.parent, mutation_seed=decided.mutation_seed))
    assert evolution.repeat(again.name) == (decided.name, body, mutation)
    assert evolution.repeat("i0000") is None  # an initial body is trained


def test_only_an_initial_body_is_checked_when_a_child_repeats_it(
    initial: list[Genome], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A tournament child's body was checked by its trainer (`breed`), so a repeat of it costs
    the coordinator no MuJoCo compile (it was a sixth of the coordinator's loop at 1,000
    workers); an initial body, which may be given by hand, is checked once."""
    checked: list[str] = []

    def counting(genome: Genome) -> bool:
        checked.append(body_hash(genome))
        return is_valid(genome)

    monkeypatch.setattr(population, "is_valid", counting)
    evolution = _evolution(initial)
    for k, child in enumerate(evolution.initial):
        evolution.birth(child.name, float(k), initial[k])
    decided = evolution.tournament()
    evolution.record(decided)
    body, mutation = breed(*evolution.to_train(decided.name))
    evolution.birth(decided.name, 7.0, body)
    for seed in (decided.mutation_seed, decided.mutation_seed):  # twice: a repeat each time
        again = evolution.tournament()
        evolution.record(replace(again, parent=decided.parent, mutation_seed=seed))
        assert evolution.repeat(again.name) == (decided.name, body, mutation)
    assert checked == []
    # a child whose first draft is an initial body: that body is checked, once
    parent = int(decided.parent[1:])
    other = (parent + 1) % len(initial)
    draft = first_draft(initial[parent], decided.mutation_seed)[0]
    founders = [draft if k == other else body for k, body in enumerate(initial)]
    evolution = _evolution(founders)
    for k, child in enumerate(evolution.initial):
        evolution.birth(child.name, float(k), founders[k])
    again = evolution.tournament()  # the same parent and seed: they depend on fitness only
    evolution.record(again)
    assert (again.parent, again.mutation_seed) == (decided.parent, decided.mutation_seed)
    evolution.repeat(again.name)
    evolution.repeat(again.name)
    assert checked == [body_hash(draft)]


def test_tournaments_pick_the_fittest_and_children_are_born_with_their_bred_body(
    initial: list[Genome],
) -> None:
    evolution = _evolution(initial)
    with pytest.raises(RuntimeError, match="initial population"):
        evolution.tournament()
    for k, child in enumerate(evolution.initial):
        assert evolution.to_train(child.name) == (initial[k], None)
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
    assert evolution.to_train(decided.name) == (parent_body, decided.mutation_seed)

    child_body, _ = breed(parent_body, decided.mutation_seed)
    member = evolution.birth(decided.name, 50.0, child_body)
    assert member is not None and member.parent == decided.parent
    assert evolution.to_train(decided.name) == (child_body, None)
    assert [m.agent for m in evolution.population] == ["i0001", "i0002", "i0003", decided.name]
    assert evolution.best() == member  # the fittest born, aged out of the population or not
    again = evolution.tournament()
    evolution.record(again)
    evolution.birth(again.name, 50.0, breed(*evolution.to_train(again.name))[0])
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
        body = breed(*live.to_train(decided.name))[0]
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
    from derl.nodes.coordinator.state import CoordinatorState, tournament_message

    from derl.rl import PPOConfig

    config = load_profile("smoke").model_copy(update={"population": 4, "tournament": 3})
    state = CoordinatorState.start(config, initial)
    template = next(m for m in examples("r") if isinstance(m, Birth))
    ppo = PPOConfig(total_steps=4096, seed=0)
    for k, child in enumerate(state.evolution.initial):
        job = TrainJob(
            run="r",
            job=f"{child.name}.1",
            child=child.name,
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
                    "child": child.name,
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
    assert list(state.waiting) == [decided.name] and not state.wants_tournament()
    genome, seed = state.evolution.to_train(decided.name)
    assert seed == decided.mutation_seed
    state.apply(
        TrainJob(
            run="r",
            job=f"{decided.name}.1",
            child=decided.name,
            node="t1",
            genome=genome,
            task="ft",
            ppo=ppo,
            parent=decided.parent,
            mutation_seed=seed,
            lease_s=10.0,
        )
    )
    assert not state.waiting and state.job_of("t1").subject == decided.name


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


def test_a_child_that_cannot_be_bred_is_no_repeat(monkeypatch: pytest.MonkeyPatch) -> None:
    """A child whose first draft is a born body but that cannot be bred at all (its parent, not
    a valid body, has three limbs in one place: no single mutation fixes that) is no repeat:
    `repeat` says so instead of raising (the coordinator's lookup raised on every WorkerReady
    that drew the child); its trainer fails the same way and the child is given up. (Breeding
    gives up after 5 draws here, not 100: 19 s of MuJoCo compiles for the same outcome.)"""
    monkeypatch.setattr(population, "MAX_DRAWS", 5)
    joint = Joint(axis="x", range=(-30, 60), gear=200)
    limb = Limb(id=0, paired=False, length=0.3, theta=0, phi=90, joints=(joint,))
    limbs = tuple(limb.model_copy(update={"id": k}) for k in range(3))
    stacked = Genome(head_density=700, limb_density=600, limbs=limbs)
    config = load_profile("smoke").model_copy(update={"population": 2, "tournament": 2})

    def decided(initial: list[Genome]) -> tuple[Evolution, Child]:
        evolution = Evolution(config, initial)
        for k, founder in enumerate(evolution.initial):
            evolution.birth(founder.name, float(1 - k), founder.genome)
        child = evolution.tournament()  # parent and seed do not depend on the bodies
        evolution.record(child)
        return evolution, child

    _, probe = decided([stacked, stacked])
    draft = first_draft(stacked, probe.mutation_seed)[0]
    order = [stacked, draft] if probe.parent == "i0000" else [draft, stacked]
    evolution, child = decided(order)
    assert evolution.draft(child.name) == body_hash(draft)  # a born body
    with pytest.raises(MutationFailed):
        breed(stacked, child.mutation_seed)
    assert evolution.repeat(child.name) is None


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
