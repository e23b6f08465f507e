"""One valid message of every type, for tests, benchmarks and documentation.

`examples(run, i)` varies the ids and numbers with `i`, so many distinct messages can be made;
`checkpoint_bytes` sets the size of the FitnessReport's (pseudo-random) checkpoint.
"""

from __future__ import annotations

import random

from derl.messages.schema import (
    Ack,
    Birth,
    Cancel,
    ChildFailed,
    Curve,
    Dropped,
    EvalJob,
    EvalResult,
    FitnessReport,
    JobFailed,
    JobLost,
    MessageBase,
    PopulationEntry,
    PopulationSnapshot,
    Quarantine,
    Reject,
    Rejection,
    Retrained,
    RunSettings,
    RunStatus,
    Tournament,
    TrainJob,
    TrainProgress,
    Undo,
    WorkerReady,
)
from derl.rl.config import PPOConfig
from derl.unimal.genome import Genome, Joint, Limb

_JOINTS = (Joint(axis="x", range=(-30, 60), gear=200), Joint(axis="y", range=(-45, 0), gear=150))

GENOME = Genome(
    head_density=700,
    limb_density=600,
    limbs=(
        Limb(id=0, paired=True, length=0.3, theta=45, phi=135, joints=_JOINTS),
        Limb(id=1, parent=0, site="end", paired=True, length=0.2, theta=0, phi=180, joints=_JOINTS),
    ),
)
"""A small valid body: one pair of two-segment legs."""


def examples(run: str = "run1", i: int = 0, checkpoint_bytes: int = 64) -> list[MessageBase]:
    """One message of each type (in `MESSAGE_TYPES` order), all of run `run`."""
    child, parent, node, job = f"a{i + 10}", f"a{i}", f"trainer-{i % 3}", f"job.{i}"
    curve = Curve(env_steps=(4096 * (i + 1), 8192 * (i + 1)), returns=(0.5 * i, -1.25 + i))
    return [
        WorkerReady(run=run, node=node, role="trainer", host="host-1", pid=1000 + i, nthread=2),
        TrainJob(
            run=run,
            job=job,
            agent=child,
            node=node,
            genome=GENOME,
            task="ft",
            ppo=PPOConfig(total_steps=5_000_000, seed=i),
            parent=parent,
            mutation="grow_limb",
            mutation_detail="pair on limb 0 end",
            lease_s=3.0,
        ),
        EvalJob(
            run=run,
            job=job,
            agent=child,
            node=node,
            genome=GENOME,
            task="patrol",
            ppo=PPOConfig(total_steps=1_000_000, seed=2**62 + i, fitness_component="reach"),
            lease_s=2.5,
        ),
        Tournament(
            run=run,
            agent=child,
            contestants=(parent, f"a{i + 1}", parent),
            fitness=(10.0 + i, 3.5, 10.0 + i),
            parent=parent,
            mutation_seed=2**40 + i,
            iteration=i,
        ),
        TrainProgress(
            run=run,
            agent=child,
            job=job,
            node=node,
            env_steps=4096 * i,
            total_steps=5_000_000,
            recent_return=None if i % 2 else 1.5 * i,
            steps_per_s=1234.5,
        ),
        FitnessReport(
            run=run,
            agent=child,
            job=job,
            node=node,
            genome=GENOME,
            fitness=123.25 + i,
            fitness_source="window",
            fitness_episodes=32,
            curve=curve,
            energy=4.5e3,
            cost_of_work=0.75,
            mass=6.25,
            episodes=160,
            env_steps=5_000_000,
            constraint_rows=61_250_000,
            wall_s=3600.5,
            steps_per_s=1388.9,
            checkpoint=random.Random(i).randbytes(checkpoint_bytes),
        ),
        Ack(run=run, of="FitnessReport", job=job, agent=child, node=node),
        EvalResult(
            run=run,
            agent=child,
            task="patrol",
            seed=7,
            steps=1_000_000,
            reward=-12.5 - i,
            cost_of_work=1.5,
            curve=curve,
            node=node,
            job=job,
        ),
        Reject(run=run, of="FitnessReport", job=job, agent=child, node=node, reason="wrong body"),
        Cancel(run=run, job=job, node=node, reason=f"{child} was born from another job"),
        JobLost(run=run, job=job, node=node, reason="no progress for 60 s"),
        JobFailed(run=run, job=job, node=node, agent=child, error="ValueError: bad things"),
        Birth(
            run=run,
            agent=child,
            parent=parent,
            job=job,
            node=node,
            birth=i + 1,
            generation=1,
            fitness=123.25 + i,
            cost_of_work=0.75,
            energy=4.5e3,
            mass=6.25,
            mutation="grow_limb",
            mutation_detail="pair on limb 0 end",
            genome=GENOME,
            episodes=160,
            constraint_rows=61_250_000,
        ),
        ChildFailed(run=run, agent=child, parent=parent, attempts=3, error="ValueError: again"),
        Quarantine(
            run=run, node=node, agent=child, jobs=(job, f"{job}b", f"{job}c"), retrain=(parent,)
        ),
        Retrained(
            run=run,
            agent=child,
            job=job,
            node=node,
            fitness=122.25 + i,
            was=123.25 + i,
            cost_of_work=0.75,
            energy=4.5e3,
            mass=6.25,
            episodes=160,
            constraint_rows=61_250_000,
        ),
        Undo(run=run, node=node, agent=child, iteration=12, voided=9),
        Dropped(run=run, agent=child, agents=(f"c{i + 4000:05d}", f"c{i + 4001:05d}")),
        Rejection(
            run=run,
            reason="wrong key",
            key=f"derl/{run}/fitness/{node}/{child}",
            sender=node,
            of="FitnessReport",
            job=job,
        ),
        RunSettings(run=run, settings='{"name": "smoke", "total": 8}'),
        PopulationSnapshot(
            run=run,
            birth_counter=i + 2,
            members=(
                PopulationEntry(agent=parent, fitness=10.0 + i, parent=None, birth=0),
                PopulationEntry(agent=child, fitness=-0.5, parent=parent, birth=i + 1),
            ),
        ),
        RunStatus(
            run=run,
            born=i + 2,
            target=4000,
            best_fitness=10.0 + i,
            best_agent=parent,
            in_flight=3,
            workers_alive=4,
            done=False,
        ),
    ]
