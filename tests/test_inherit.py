"""Inheritance (`inherit: parent`): a child's controller starts from its parent's trained weights
where their bodies' parts match (`derl.rl.inherit`), fresh ones where they do not; the trainer
gets the parent's checkpoint from the coordinator over Zenoh and trains only from the bytes the
job names; a training of the same job again gives the same bits."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch
from nodes_fixtures import REPO, LocalRun, Processes, assert_born_once, journaled

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.evolution import Evolution, load_profile
from derl.lifetime import inheritance, learn
from derl.messages import Birth, FitnessReport, ParentWeights, TrainJob
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.worker import node as worker_node
from derl.rl.checkpoint import Checkpoint
from derl.rl.network import ActorCritic
from derl.rl.normalize import ObsNormalizer
from derl.unimal import Genome, body_hash, mutate, sample_population

EXAMPLE = REPO / "examples" / "inherit.yaml"
FIRST = "actor.branches.proprioception.0.weight"


def _bodies(op: str) -> tuple[Genome, Genome]:
    parent = sample_population(1, np.random.default_rng(3))[0]
    child, _ = mutate(parent, np.random.default_rng(0), op=op)
    return parent, child


def _env(genome: Genome) -> UnimalEnv:
    return UnimalEnv(genome, make_task("ft"), EnvConfig(num_envs=1))


@pytest.mark.parametrize("op", ["grow_limb", "delete_limb"])
def test_a_child_starts_with_its_parents_weights_where_their_parts_match(op: str) -> None:
    parent, child = _bodies(op)
    old, new = _env(parent), _env(child)
    torch.manual_seed(7)  # a parent's "trained" network and statistics: any other weights
    net = ActorCritic(old.obs_spaces, old.action_dim)
    with torch.no_grad():
        net.log_std.normal_()
    norm = ObsNormalizer(old.obs_spaces, 10.0)
    seen = np.random.default_rng(1).normal(3.0, 2.0, (50, old.obs_spaces["proprioception"]))
    norm.update({"proprioception": seen})
    config = load_profile("smoke").training_ppo()
    checkpoint = Checkpoint.capture(net, norm, config).to_bytes()

    torch.manual_seed(11)
    fresh = ActorCritic(new.obs_spaces, new.action_dim)
    torch.manual_seed(11)
    started = ActorCritic(new.obs_spaces, new.action_dim)
    started_norm = ObsNormalizer(new.obs_spaces, 10.0)
    inheritance(parent, checkpoint, "ft", new)(started, started_norm)

    theirs, mine = net.state_dict(), started.state_dict()
    columns = {name: k for k, name in enumerate(old.proprioception_labels)}
    shared = [name for name in new.proprioception_labels if name in columns]
    assert 0 < len(shared) < max(len(new.proprioception_labels), len(columns))
    for k, name in enumerate(new.proprioception_labels):
        source = (
            theirs[FIRST][:, columns[name]] if name in columns else fresh.state_dict()[FIRST][:, k]
        )
        assert torch.equal(mine[FIRST][:, k], source), name
        if name in columns:
            assert (
                started_norm.stats["proprioception"].mean[k]
                == norm.stats["proprioception"].mean[columns[name]]
            )
        else:
            assert started_norm.stats["proprioception"].mean[k] == 0.0
    assert started_norm.stats["proprioception"].count == norm.stats["proprioception"].count
    actions = {name: k for k, name in enumerate(old.action_labels)}
    for k, name in enumerate(new.action_labels):
        expected = theirs["log_std"][actions[name]] if name in actions else torch.tensor(0.0)
        assert torch.equal(mine["log_std"][k], expected), name
    for name in ("actor.branches.proprioception.2.weight", "critic.branches.proprioception.0.bias",
                 "value_head.weight"):  # fmt: skip
        assert torch.equal(mine[name], theirs[name])


def _job(parent: Genome, child: Genome, sha256: bytes) -> TrainJob:
    return TrainJob(
        run="r", job="c00000.1", agent="c00000", node="t0", genome=child, task="ft",
        ppo=load_profile("smoke").training_ppo(), parent="i0000", mutation="grow_limb",
        lease_s=30.0, inherit=ParentWeights(genome=parent, sha256=sha256),
    )  # fmt: skip


def test_a_trainer_trains_only_from_the_parents_checkpoint_its_job_names(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Bytes of another SHA-256 than the job's, or none in time, fail the job with the reason."""
    monkeypatch.setattr(worker_node, "PARENT_WAIT_S", 0.2)
    monkeypatch.setattr(worker_node, "PARENT_ASK_S", (0.2, 0.05))
    parent, child = _bodies("grow_limb")
    worker = worker_node.Worker("r", "t0", "trainer")
    with open_session(ZenohOptions()) as session:
        worker.bus = Bus(session, "r")
        job = _job(parent, child, hashlib.sha256(b"the parent's").digest())
        with pytest.raises(worker_node.NoParentWeights, match="no checkpoint of i0000 came"):
            worker._parent_weights(job)
        answer = session.declare_queryable(
            worker.bus.keys.checkpoint("i0000"),
            lambda query: query.reply(worker.bus.keys.checkpoint("i0000"), b"another's"),
        )
        with pytest.raises(worker_node.NoParentWeights, match="has SHA-256"):
            worker._parent_weights(job)
        good = job.model_copy(update={"inherit": ParentWeights(
            genome=parent, sha256=hashlib.sha256(b"another's").digest())})  # fmt: skip
        assert worker._parent_weights(good) == b"another's"
        answer.undeclare()


def test_an_inheriting_evolution_over_zenoh_trains_children_from_their_parents_weights(
    tmp_path: Path,
) -> None:
    """examples/inherit.yaml (smoke's 8 bodies, half its budget), a real coordinator and two
    trainers: every tournament's child is ordered with its parent's body and checkpoint hash,
    and training its job again from the parent's file gives its checkpoint to the bit (from
    scratch: another)."""
    local = LocalRun(tmp_path / "run", EXAMPLE)
    processes = Processes(tmp_path / "logs")
    try:
        coordinator = processes.start(
            "coordinator",
            [*local.coordinator(), "--set", "eval_top=0", "--set", "train_steps=4096"],
        )
        for k in range(2):
            processes.start(f"t{k}", local.trainer(f"t{k}"))
        assert processes.finish(coordinator, timeout=180) == 0, processes.log("coordinator")
    finally:
        processes.close()
    assert_born_once(local.dir, load_profile(str(EXAMPLE)).total)
    files = local.dir / "checkpoints"
    digests = {r.agent: r.checkpoint for r in journaled(local.dir, FitnessReport)}
    children = [job for job in journaled(local.dir, TrainJob) if job.parent is not None]
    assert children and all(job.inherit is not None for job in children)
    genomes = {birth.agent: birth.genome for birth in journaled(local.dir, Birth)}
    for job in children:
        assert job.inherit is not None
        assert job.inherit.genome == genomes[job.parent]
        parent_file = (files / f"{job.parent}.pt").read_bytes()
        assert job.inherit.sha256 == hashlib.sha256(parent_file).digest()
    job = children[0]
    assert job.inherit is not None and job.parent is not None
    parent_file = (files / f"{job.parent}.pt").read_bytes()
    _, again = learn(job.genome, job.task, job.ppo, parent=(job.inherit.genome, parent_file))
    assert hashlib.sha256(again.checkpoint.to_bytes()).digest() == digests[job.agent]
    _, scratch = learn(job.genome, job.task, job.ppo)
    assert not torch.equal(scratch.checkpoint.weights[FIRST], again.checkpoint.weights[FIRST])


@pytest.mark.parametrize("inherit", ["none", "parent"])
def test_a_repeat_needs_the_same_parent_training_where_children_inherit(inherit: str) -> None:
    """A child whose body was born before is that body's repeat (born with its result, not
    trained) only where its training would be the same: from scratch, the same body; inheriting,
    the same body from a parent whose own training was the same."""
    config = load_profile("smoke", inherit=inherit)
    evolution = Evolution(config)
    for k, child in enumerate(evolution.initial):
        evolution.birth(child.name, float(k), evolution.genomes[child.name])
    decided = evolution.tournament()
    assert decided is not None
    evolution.record(decided)
    genome, _ = evolution.body(decided.name)
    initial = evolution.initial[0].name
    assert evolution.body_key(initial) == body_hash(evolution.genomes[initial])
    assert (evolution.body_key(decided.name) == body_hash(genome)) == (inherit == "none")
