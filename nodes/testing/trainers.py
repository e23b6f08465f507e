"""Simulated trainers' results, for tools and tests that drive the coordinator's own handlers in
their process without a bus: reports that train nothing, each child's own policy, a recorder
of what the coordinator publishes, and a whole run driven by simulated trainers (`simulate_run`).

A report is accepted as a real trainer's (its job's body, env steps within the job's budget, a
fitness within the world's bound, a policy that loads for the body), so the coordinator takes the
same paths as in a run."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import torch

from derl.evolution import EvolutionConfig
from derl.lifetime import ppo_config
from derl.messages import (
    Ack,
    Cancel,
    Curve,
    FitnessReport,
    MessageBase,
    Reject,
    TrainJob,
    WorkerReady,
    decode,
    encode,
)
from derl.nodes.coordinator.node import Coordinator, Liveliness
from derl.nodes.coordinator.run.rules import EvolutionRules
from derl.policy_check import expected_spaces
from derl.rl.checkpoint import Checkpoint
from derl.rl.network import ActorCritic
from derl.rl.normalize import ObsNormalizer
from derl.unimal import Genome, body_hash


class Recorder:
    """A coordinator's publisher (`Coordinator(..., publisher=Recorder())`) in place of the bus:
    what it publishes, in order."""

    def __init__(self) -> None:
        self.messages: list[MessageBase] = []

    def publish(self, msg: MessageBase, data: bytes | None = None) -> None:
        self.messages.append(msg)


def untrained_policy(genome: Genome, world: str, seed: int = 0) -> bytes:
    """A checkpoint of `genome`'s network in `world` with initial weights drawn from `seed`
    (the same bytes for the same arguments): a policy that passes `policy_problem`
    (`derl.policy_check`), for tests and benchmarks that stand in for a trainer."""
    spaces, actions = expected_spaces(genome, world)
    torch.manual_seed(seed)
    net = ActorCritic(spaces, actions)
    config = ppo_config(world, 4096, seed, num_envs=16)
    return Checkpoint.capture(net, ObsNormalizer(spaces, config.obs_clip), config).to_bytes()


@cache
def policy_of(child: str, genome: Genome, world: str) -> bytes:
    """The policy a simulated trainer reports for `child` of body `genome`: an untrained one, its
    weights drawn from the child's name (each child's own; tens of kB, so a write spans pages);
    made once (its orthogonal weights cost tens of ms, and checks compare them again)."""
    seed = int.from_bytes(hashlib.sha256(child.encode()).digest()[:4], "little")
    return untrained_policy(genome, world, seed)


def fake_report(run: str, job: TrainJob, fitness: float, points: int = 100) -> FitnessReport:
    """A result for `job` that trained nothing: its body (bred by the coordinator), `fitness`, a
    learning curve of `points` points and an untrained policy of the body."""
    return FitnessReport(
        run=run, agent=job.agent, job=job.job, node=job.node, genome=job.genome, fitness=fitness,
        fitness_source="window", fitness_episodes=10,
        curve=Curve(env_steps=tuple(range(4096, 4096 * (points + 1), 4096)),
                    returns=tuple(float(k) for k in range(points))),
        energy=1.0, cost_of_work=1.0, mass=1.0, episodes=10, env_steps=409600, wall_s=1.0,
        steps_per_s=1.0, checkpoint=untrained_policy(job.genome, job.task),
    )  # fmt: skip


def honest(genome: Genome) -> float:
    """The fitness of a body as every honest training finds it (training is deterministic):
    drawn from its `body_hash`."""
    return int.from_bytes(bytes.fromhex(body_hash(genome))[:2], "little") / 100


def lies_about(child: str, rate: float) -> bool:
    """Whether a liar that lies on a share `rate` of its reports lies about `child` (drawn from
    the child's name)."""
    draw = int.from_bytes(hashlib.sha256(f"lie {child}".encode()).digest()[:8], "little")
    return draw < rate * 2**64


def honest_report(job: TrainJob, lie: float = 0.0) -> FitnessReport:
    """`job`'s report with its body's `honest` fitness plus `lie` (a liar's: not 0), 4-19
    episodes drawn from the body too (the cluster timing's duration), and the child's own policy
    (`policy_of`)."""
    episodes = 4 + int(honest(job.genome) * 100) % 16
    return FitnessReport(
        run=job.run, agent=job.agent, job=job.job, node=job.node, genome=job.genome,
        fitness=honest(job.genome) + lie, fitness_source="window", fitness_episodes=4,
        curve=Curve(env_steps=(job.steps,), returns=(1.0,)), energy=2.0, cost_of_work=0.5,
        mass=3.0, episodes=episodes, env_steps=job.steps, wall_s=1.0, steps_per_s=1.0,
        checkpoint=policy_of(job.agent, job.genome, job.task),
    )  # fmt: skip


@dataclass
class Trainers:
    """Simulated trainers of run `run`: each answers its job at once (`honest_report`, plus 1.0
    where the `liar` lies: on a share `rate` of its children, `lies_about`) and, once answered,
    asks for work once: an idle one then waits among the coordinator's idle workers for its
    next job."""

    run: str
    names: list[str]
    liar: str | None = None
    rate: float = 1.0
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
                lies = node == self.liar and lies_about(msg.agent, self.rate)
                out.append(honest_report(msg, 1.0 if lies else 0.0))
            elif isinstance(msg, Ack | Reject | Cancel) and msg.job == self.jobs.get(node, msg).job:
                del self.jobs[node]
        return out

    def asking(self) -> list[MessageBase]:
        new = [n for n in self.names if n not in self.jobs and n not in self.asked]
        self.asked.update(new)
        return [WorkerReady(run=self.run, node=n, role="trainer", host="sim", pid=1) for n in new]


def simulate_run(
    run: str,
    folder: Path,
    config: EvolutionConfig,
    names: list[str],
    liar: str | None = None,
    rounds: int = 400,
    rate: float = 1.0,
) -> Coordinator:
    """The run of `config` in `folder` (begun or not) to its end (every child born, none waiting
    to be trained again, its results written) by the simulated `Trainers` named `names` (`liar`
    lies on a share `rate` of its reports); the coordinator, closed."""
    heard = Recorder()
    coordinator = Coordinator(run, folder, EvolutionRules(run, folder, config), publisher=heard)
    trainers = Trainers(run, names, liar, rate)
    for node in names:
        coordinator.take(Liveliness("trainer", node, True))
    try:
        inbox = trainers.asking()
        for _ in range(rounds):
            if coordinator.state.finished:
                coordinator.rules.finish()
                return coordinator
            for msg in inbox:
                coordinator.take(decode(encode(msg)))
            coordinator.assign_idle()
            coordinator.settle()
            inbox = trainers.answer(heard.messages) + trainers.asking()
            heard.messages.clear()
        raise AssertionError(f"the run did not finish: {len(coordinator.state.births)} born")
    finally:
        coordinator.close()
