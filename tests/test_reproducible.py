"""A run is a function of its profile and seed, in either timing (window, cluster): the same
births on 1 trainer or 3, with a trainer SIGKILLed and the coordinator SIGKILLed and resumed, with
real processes on real Zenoh (loopback, multicast off); and, without a bus, whatever order the
trainings finish in."""

from __future__ import annotations

import hashlib
import json
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from nodes_fixtures import REPO, LocalRun, Processes, assert_born_once, journaled
from pydantic import ValidationError

from derl.evolution import Evolution, EvolutionConfig, fingerprint, load_profile
from derl.evolution.timing import ClusterClock
from derl.lifetime import learn, ppo_config
from derl.messages import Birth
from derl.nodes.journal.history import load_history
from derl.nodes.testing.waiting import wait_until
from derl.rl.config import SAVED
from derl.unimal import Genome, body_hash, canonical_genome, sample_population

PROFILE = {
    "population": 4,
    "in_flight": 2,
    "tournament": 2,
    "total": 8,  # smoke's: 4 initial bodies and 4 children
    "train_steps": 4096,  # 2 PPO iterations of 16 envs x 128 steps, under a second a body
}

Facts = list[tuple[str, str | None, int, str, str]]


def _births(run_dir: Path) -> Facts:
    """(child, parent, generation, the fitness's bits, body) of every birth, in child order."""
    born = journaled(run_dir, Birth)
    return sorted(
        (b.agent, b.parent, b.generation, b.fitness.hex(), body_hash(b.genome)) for b in born
    )


def _run(tmp_path: Path, trainers: int, timing: str, faults: bool = False) -> Path:
    """A run of PROFILE in `timing` with `trainers` trainers until it finishes; with `faults`, a
    trainer is SIGKILLed mid-job (and another started) and then the coordinator (and started
    again)."""
    folder = tmp_path / f"{trainers}{'-faults' if faults else ''}"
    folder.mkdir()
    local = LocalRun.at(folder, **PROFILE, timing=timing)
    processes = Processes(local.dir.parent / "logs")
    try:
        coordinator = processes.start("coordinator", local.coordinator())
        for k in range(trainers):
            processes.start(f"t{k}", local.trainer(f"t{k}"))
        if faults:
            wait_until(lambda: len(journaled(local.dir, Birth)) >= 2, 120, "2 births")
            processes.kill("t0")  # mid-job: the other trainers are busy too
            processes.start("t9", local.trainer("t9"))
            wait_until(lambda: len(journaled(local.dir, Birth)) >= 5, 120, "5 births")
            processes.kill("coordinator")
            coordinator = processes.start("coordinator", local.coordinator())
        assert processes.finish(coordinator, timeout=240) == 0, processes.log("coordinator")
    finally:
        processes.close()
    assert_born_once(local.dir, PROFILE["total"])
    return local.dir


@pytest.mark.slow
@pytest.mark.parametrize("timing", ["window", "cluster"])
def test_the_same_seed_gives_the_same_births_on_any_number_of_trainers_and_after_crashes(
    tmp_path: Path, timing: str
) -> None:
    alone = _run(tmp_path, trainers=1, timing=timing)
    crashed = _run(tmp_path, trainers=3, timing=timing, faults=True)
    expected = _births(alone)
    assert len(expected) == PROFILE["total"]
    assert _births(crashed) == expected
    prints = {load_history(d).fingerprint() for d in (alone, crashed)}
    assert len(prints) == 1, prints


def _evolve(config_changes: dict[str, object], trainers: int, seed: int) -> list[tuple]:
    """An evolution of 40 children run by `trainers` simulated trainers whose trainings finish in
    a random order (`seed`); a body's fitness and its training's counts (the cluster timing's
    duration) are functions of the body (training is deterministic), and one child in 17 is
    given up. The births as (child, parent, fitness), in child order."""
    config = load_profile("smoke", list(config_changes.items()), total=40)
    evolution = Evolution(config, sample_population(config.population, np.random.default_rng(1)))
    rng = random.Random(seed)
    waiting = [child.name for child in evolution.initial]
    training: list[str] = []
    while not evolution.complete:
        while len(training) < trainers:
            if waiting:
                training.append(waiting.pop(0))
                continue
            started = evolution.settled + len(training)
            open_ended = config.end == "released"  # it breeds until N bodies finished
            decided = evolution.tournament() if open_ended or started < config.total else None
            if decided is None:
                break
            evolution.record(decided)
            evolution.body(decided.name)
            training.append(decided.name)
        done = training.pop(rng.randrange(len(training)))
        genome = evolution.genomes[done]
        drawn = int(body_hash(genome)[:6], 16)
        if drawn % 17 == 0 and evolution.index[done] >= config.population:
            evolution.give_up(done)
            continue
        work = (drawn % 50, len(genome.limbs) * 10**7)  # episodes, constraint rows
        evolution.birth(done, drawn / 1e5, genome, work=work)
        if (dropped := evolution.released_end()) is not None:
            assert set(training) <= set(dropped)  # all in flight then finish past the N-th
            evolution.drop(dropped)
    born = sorted(evolution.born, key=lambda m: evolution.index[m.agent])
    return [(m.agent, m.parent, m.fitness) for m in born]


@pytest.mark.parametrize("timing", ["window", "cluster"])
def test_births_do_not_depend_on_the_trainers_or_the_order_trainings_finish_in(
    timing: str,
) -> None:
    windowed = {"population": 8, "in_flight": 4, "tournament": 3, "timing": timing}
    expected = _evolve(windowed, trainers=1, seed=0)
    for trainers, seed in [(2, 1), (4, 2), (4, 3), (9, 4)]:
        assert _evolve(windowed, trainers, seed) == expected, (trainers, seed)
    if timing == "window":
        free = {**windowed, "in_flight": 0}  # the released code's rule: it depends on both
        assert _evolve(free, 4, 2) != _evolve(free, 4, 3)


def test_the_released_end_keeps_the_n_first_to_finish_whatever_the_trainers() -> None:
    """`end: released`: the virtual workers breed while fewer than N bodies finished, and the run
    keeps the N that finished first (the released code drops what is in flight when its N-th body
    is saved): the same N births on 1 trainer or 9 and in any order, and not the first N bred."""
    released = {"population": 8, "in_flight": 4, "tournament": 3, "timing": "cluster",
                "end": "released"}  # fmt: skip
    expected = _evolve(released, trainers=1, seed=0)
    assert len(expected) == 40
    for trainers, seed in [(2, 1), (4, 2), (9, 4)]:
        assert _evolve(released, trainers, seed) == expected, (trainers, seed)
    every_child = _evolve({**released, "end": "all"}, trainers=4, seed=2)
    assert {b[0] for b in every_child} != {b[0] for b in expected}
    assert every_child[: len(every_child) // 2] == expected[: len(every_child) // 2]
    with pytest.raises(ValidationError, match="end released needs timing cluster"):
        load_profile("smoke", [("end", "released")])


def test_the_pool_is_the_latest_born_of_the_first_children_in_child_order() -> None:
    config = load_profile("smoke").model_copy(
        update={"population": 3, "in_flight": 2, "tournament": 2, "total": 20}
    )
    evolution = Evolution(config, sample_population(3, np.random.default_rng(1)))
    assert evolution.tournament() is None  # nobody born
    evolution.birth("i0002", 5.0, evolution.genomes["i0002"])
    assert evolution.tournament() is None  # child 3 needs child 0 (3 - W) settled first
    evolution.birth("i0000", 1.0, evolution.genomes["i0000"])
    first = evolution.tournament()
    assert first is not None and set(first.contestants) == {"i0000"}  # the first child alone
    evolution.record(first)
    assert evolution.tournament() is None  # child 4 needs children 0-1: i0001 trains still
    evolution.give_up("i0001")
    second = evolution.tournament()
    assert second is not None and set(second.contestants) <= {"i0000"}  # i0001 was given up
    evolution.record(second)
    evolution.birth(first.name, 3.0, evolution.body(first.name)[0])
    third = evolution.tournament()  # child 5: the P latest born of children 0-2
    assert third is not None and set(third.contestants) <= {"i0000", "i0002"}
    assert [m.agent for m in evolution.population] == ["i0000", "i0002", first.name]


def test_the_cluster_timing_breeds_when_a_virtual_worker_comes_free_from_the_latest_finished():
    """2 workers, P 3, every training at least 10 µs: initial bodies 0 and 2 are worker 0's, 1 is
    worker 1's; a child bred later that trains fast joins before a slow initial body."""
    clock = ClusterClock(workers=2, initial=3, population=3, least=10)
    clock.done(1, 15, born=True)
    assert clock.breeding(0) is None  # body 0 might still finish before 15
    clock.done(0, 12, born=True)
    assert clock.breeding(0) == (
        15,
        [0, 1],
        2,
    )  # worker 1 is free at 15; body 2 ends at 22 or later
    assert clock.breeding(1) is None  # child 3 started at 15 on worker 1 and trains still
    clock.done(3, 11, born=True)
    assert clock.breeding(1) is None  # body 2 (from 12) might end before child 3 (at 26)
    clock.done(2, 20, born=True)
    assert clock.breeding(1) == (26, [0, 1, 3], 3)  # body 2 ends at 32: not in it yet
    config = load_profile("smoke", [("timing", "cluster")])
    assert config.training_time.least(1000) < config.training_time.duration(1000, 1, 1)
    with pytest.raises(ValidationError, match="timing cluster needs"):
        load_profile("smoke", [("timing", "cluster"), ("in_flight", 0)])


def test_a_fingerprint_is_of_the_births_in_child_order_and_sees_every_bit() -> None:
    body = sample_population(1, np.random.default_rng(1))[0]
    births = [("i0000", None, 0, 1.5, body), ("c00000", "i0000", 1, 2.0, body)]
    assert fingerprint(births) == fingerprint(births[::-1])
    assert len(fingerprint(births)) == 16
    nudged = [births[0], ("c00000", "i0000", 1, np.nextafter(2.0, 3.0), body)]
    assert fingerprint(nudged) != fingerprint(births)


def test_training_gives_the_same_bits_in_any_process_first_or_last() -> None:
    """The fitness and the checkpoint's bytes of a training are the same in a fresh process and
    after another training in the same one (nothing of a training outlives it)."""
    a, b = sample_population(2, np.random.default_rng(5))
    config = ppo_config("vt", steps=4096, seed=1409, num_envs=16)

    def bits(genome: Genome) -> tuple[str, str]:
        summary, result = learn(genome, "vt", config)
        return summary.fitness.hex(), hashlib.sha256(result.checkpoint.to_bytes()).hexdigest()

    first = bits(a)
    bits(b)
    assert bits(a) == first
    fresh = subprocess.run(
        [sys.executable, "-c", FRESH, a.model_dump_json()],
        capture_output=True, text=True, check=True, cwd=REPO,
    )  # fmt: skip
    assert fresh.stdout.split() == list(first)


FRESH = """
import hashlib, sys
from derl.lifetime import learn, ppo_config
from derl.rl.config import SAVED
from derl.unimal import Genome
summary, result = learn(Genome.model_validate_json(sys.argv[1]), "vt",
                        ppo_config("vt", steps=4096, seed=1409, num_envs=16))
print(summary.fitness.hex(), hashlib.sha256(result.checkpoint.to_bytes()).hexdigest())
"""


def test_every_body_of_a_run_is_in_canonical_form() -> None:
    """Equal bodies are equal genomes, so a repeat's result is exactly what training it gives."""
    config = load_profile("smoke").model_copy(update={"total": 30})
    initial = sample_population(config.population, np.random.default_rng(2))
    evolution = Evolution(config, [_renumbered(g) for g in initial])
    for k, child in enumerate(evolution.initial):
        assert child.genome == canonical_genome(initial[k])
        evolution.birth(child.name, float(k), child.genome)
    for _ in range(10):
        decided = evolution.tournament()
        evolution.record(decided)
        body, _ = evolution.body(decided.name)
        assert body == canonical_genome(body)
        evolution.birth(decided.name, 1.0, body)


def _renumbered(genome: Genome) -> Genome:
    """The same body with its limb ids shifted and its entries reversed."""
    shift = {limb.id: limb.id + 10 for limb in genome.limbs}
    limbs = tuple(
        limb.model_copy(update={"id": shift[limb.id], "parent": shift.get(limb.parent)})
        for limb in reversed(genome.limbs)
    )
    return Genome.model_validate(
        {**genome.model_dump(), "limbs": [limb.model_dump() for limb in limbs]}
    )


def test_a_window_must_be_smaller_than_the_population_and_old_runs_resume_free_running() -> None:
    with pytest.raises(ValidationError, match=r"in_flight \(16\) >= population \(16\)"):
        load_profile("demo", [("in_flight", 16)])
    saved = json.loads(load_profile("demo").model_dump_json())
    del saved["in_flight"]  # a profile.json written before the window existed
    assert EvolutionConfig.model_validate(saved, context=SAVED).in_flight == 0
    with pytest.raises(ValidationError, match="in_flight"):
        EvolutionConfig.model_validate(saved)  # a profile of the user's gets the default, 288


def test_a_run_extended_with_more_bodies_gives_the_births_of_a_run_that_long_from_the_start(
    tmp_path: Path,
) -> None:
    """`derl run --set total=N --extend` on a finished run raises its saved total, and the run
    goes on to the births a run of N had from the start (simulated trainers, no bus); another
    value of a setting on a run begun is refused, naming the setting and both values."""
    from derl.nodes.cli.main import build_parser
    from derl.nodes.cli.options import profile_from
    from derl.nodes.cli.run import resumed_config
    from derl.nodes.errors import USAGE, DerlError
    from derl.nodes.testing.trainers import simulate_run

    window = ["population=4", "in_flight=2", "tournament=2", "eval_top=0", "eval_tasks=[]"]

    def config_of(run_dir: Path, *flags: str) -> EvolutionConfig:
        argv = ["run", *(f"--set={s}" for s in window), *flags, "--run-dir", str(run_dir)]
        args = build_parser().parse_args(argv)
        return resumed_config(args, run_dir, profile_from(args))

    names = ["t0", "t1", "t2"]
    whole, extended = tmp_path / "whole", tmp_path / "extended"
    simulate_run("r", whole, config_of(whole, "--set=total=12"), names)
    simulate_run("r", extended, config_of(extended, "--set=total=8"), names)
    assert len(load_history(extended).births) == 8
    with pytest.raises(DerlError, match=r"--set total=12: the run in .* has total 8 \(--extend"):
        config_of(extended, "--set=total=12")
    with pytest.raises(DerlError, match=r"tournament=3: the run in .* has tournament 2") as no:
        config_of(extended, "--set=total=8", "--set=tournament=3")
    assert no.value.code == USAGE
    config = config_of(extended, "--set=total=12", "--extend")
    assert config.total == 12 and config_of(extended, "--set=total=12").total == 12  # saved
    simulate_run("r", extended, config, names[:2])
    assert _births(extended) == _births(whole) and len(_births(whole)) == 12
    assert load_history(extended).fingerprint() == load_history(whole).fingerprint()
    settings = [json.loads(s) for s in load_history(extended).settings]  # the extension, journaled
    assert [s["total"] for s in settings] == [8, 12], settings


def test_the_coordinator_ends_a_run_as_the_released_code_did_on_any_trainers_and_resumed(
    tmp_path: Path,
) -> None:
    """`end: released` in the coordinator's own handlers, driven by simulated trainers (no bus;
    each body's episodes, and so its virtual duration, its own): the run keeps the N bodies
    that finished first in virtual time and drops what was bred past them (a Dropped, their
    jobs cancelled): the same births with 1 trainer and 3, and with a coordinator started on the
    journal cut just before the Dropped."""
    from derl.messages import Dropped
    from derl.nodes.journal.segments import JournalWriter, replay
    from derl.nodes.testing.trainers import simulate_run

    config = load_profile("smoke", [("timing", "cluster"), ("end", "released")],
                          population=6, in_flight=4, total=20, eval_top=0)  # fmt: skip
    one = simulate_run("r", tmp_path / "one", config, ["t0"])
    three = simulate_run("r", tmp_path / "three", config, ["t0", "t1", "t2"])
    for run in (one, three):
        assert len(run.state.births) == 20 and run.state.evolution.complete
        assert run.state.fingerprint() == one.state.fingerprint()
    journal = list(replay(tmp_path / "three"))
    (dropped,) = [m for m in journal if isinstance(m, Dropped)]
    assert dropped.agents and not set(dropped.agents) & set(three.state.born)
    assert dropped.agent in three.state.born
    cut = tmp_path / "cut"
    (cut / "journal").mkdir(parents=True)
    writer = JournalWriter(cut / "journal" / "segment-0000.mcap")
    for msg in journal[: journal.index(dropped)]:
        writer.write(msg)
    writer.close()
    resumed = simulate_run("r", cut, config, ["t0", "t1"])
    assert resumed.state.fingerprint() == one.state.fingerprint()
    assert load_history(cut).fingerprint() == one.state.fingerprint()

    from derl.nodes.cli.main import build_parser
    from derl.nodes.cli.options import profile_from
    from derl.nodes.cli.run import resumed_config
    from derl.nodes.errors import DerlError

    changes = ["timing=cluster", "end=released", "population=6", "in_flight=4", "eval_top=0"]
    argv = ["run", *(f"--set={s}" for s in changes), "--set=total=30", "--extend"]
    args = build_parser().parse_args([*argv, "--run-dir", str(tmp_path / "three")])
    with pytest.raises(DerlError, match=r"end: released.*cannot go on to more"):
        resumed_config(args, tmp_path / "three", profile_from(args))
