"""The message models of the bus (docs/architecture.md), one frozen pydantic model per type.

Every message carries `schema_version`, its `type` (the discriminator, equal to the class name)
and the `run` it belongs to. Unknown fields and out-of-range values are validation errors. Ids
are the same throughout: `node` a worker, `job` one assignment, `child`/`agent` a body, `parent`
the body it was mutated from (None for the initial population).
"""

from __future__ import annotations

from typing import Annotated, Final, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from derl.rl.config import PPOConfig
from derl.unimal.genome import Genome
from derl.unimal.mutations import OPERATORS
from messages.types import (
    MAX_CHECKPOINT_BYTES,
    MAX_ITEMS,
    Count,
    Finite,
    Id,
    Measure,
    NonNegative,
    Positive,
    Seed,
    Steps,
    Text,
)

SCHEMA_VERSION: Final = 3

FitnessSource = Literal["window", "last_episodes", "unfinished"]
"""As `derl.rl.episodes.FitnessSource`: "window" (episodes finished in the last window of steps,
the definition), "last_episodes" (none there: the last finished ones), "unfinished" (none at all:
the partial sums of the running episodes)."""

LeaseSeconds = Annotated[float, Field(gt=0, le=86_400, allow_inf_nan=False)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MessageBase(_Model):
    """What every message carries."""

    schema_version: Literal[SCHEMA_VERSION] = SCHEMA_VERSION
    type: str
    run: Id


class Curve(_Model):
    """A learning curve: mean return after each number of env steps (steps never decrease)."""

    env_steps: Annotated[tuple[Count, ...], Field(max_length=MAX_ITEMS)] = ()
    returns: Annotated[tuple[Finite, ...], Field(max_length=MAX_ITEMS)] = ()

    @model_validator(mode="after")
    def _aligned(self) -> Curve:
        if len(self.env_steps) != len(self.returns):
            raise ValueError(
                f"{len(self.env_steps)} env_steps but {len(self.returns)} returns: one each"
            )
        if any(a > b for a, b in zip(self.env_steps, self.env_steps[1:], strict=False)):
            raise ValueError("env_steps must not decrease")
        return self


class Member(_Model):
    """One agent of the population."""

    agent: Id
    fitness: Finite
    parent: Id | None = None
    birth: Count


class WorkerReady(MessageBase):
    """An idle trainer or evaluator asking for work (repeated until it gets some)."""

    type: Literal["WorkerReady"] = "WorkerReady"
    node: Id
    role: Literal["trainer", "evaluator"]
    host: Annotated[str, Field(min_length=1, max_length=253)]
    pid: Annotated[int, Field(ge=1, le=2**32)]
    nthread: Annotated[int, Field(ge=1, le=4096)] = 1


class TrainJob(MessageBase):
    """The coordinator's order to `node`: train `child` from scratch in `task` with `ppo`.

    The child's body is `genome`, or, when `mutation_seed` is set (a tournament's child not yet
    born), `derl.evolution.breed(genome, mutation_seed)`: `genome` is then the parent's body and
    the trainer breeds the child itself (deterministic: every attempt gets the same body). `ppo`
    is the whole learning configuration (budget, seed, copies, hyperparameters), as saved with
    the run, so a resumed run trains as it started whatever the code's defaults are now.
    """

    type: Literal["TrainJob"] = "TrainJob"
    job: Id
    child: Id
    node: Id
    genome: Genome
    task: Id
    ppo: PPOConfig
    parent: Id | None = None
    mutation_seed: Seed | None = None
    lease_s: LeaseSeconds

    @property
    def steps(self) -> int:
        return self.ppo.total_steps

    @property
    def seed(self) -> int:
        return self.ppo.seed

    @model_validator(mode="after")
    def _bred_from_parent(self) -> TrainJob:
        if self.mutation_seed is not None and self.parent is None:
            raise ValueError("a mutation_seed needs the parent it mutates")
        return self


class EvalJob(MessageBase):
    """The coordinator's order to `node`: train `agent`'s body from scratch in a test task with
    `ppo` (its budget and seed) and report the score."""

    type: Literal["EvalJob"] = "EvalJob"
    job: Id
    agent: Id
    node: Id
    genome: Genome
    task: Id
    ppo: PPOConfig
    lease_s: LeaseSeconds

    @property
    def steps(self) -> int:
        return self.ppo.total_steps

    @property
    def seed(self) -> int:
        return self.ppo.seed


class Tournament(MessageBase):
    """A decision, recorded as a fact: the contestants, the winner (parent) and the seed of the
    child's mutation (`derl.evolution.breed`; its FitnessReport names the mutation). The rule
    that made it is `derl.evolution.Evolution.tournament`; the wire only carries the outcome.

    `iteration` counts the tournaments of the run (0 for the first).
    """

    type: Literal["Tournament"] = "Tournament"
    child: Id
    contestants: Annotated[tuple[Id, ...], Field(min_length=1, max_length=10_000)]
    fitness: Annotated[tuple[Finite, ...], Field(min_length=1, max_length=10_000)]
    parent: Id
    mutation_seed: Seed
    iteration: Count

    @model_validator(mode="after")
    def _one_fitness_each(self) -> Tournament:
        if len(self.contestants) != len(self.fitness):
            raise ValueError(
                f"{len(self.contestants)} contestants but {len(self.fitness)} fitness values"
            )
        return self


class TrainProgress(MessageBase):
    """A trainer's periodic report on a job in progress."""

    type: Literal["TrainProgress"] = "TrainProgress"
    child: Id
    job: Id
    node: Id
    env_steps: Count
    total_steps: Steps
    recent_return: Finite | None = None
    steps_per_s: NonNegative

    @model_validator(mode="after")
    def _within_budget(self) -> TrainProgress:
        if self.env_steps > self.total_steps:
            raise ValueError(f"env_steps {self.env_steps} > total_steps {self.total_steps}")
        return self


class FitnessReport(MessageBase):
    """The outcome of a training job, re-sent until acknowledged; carries the body that was
    trained, the mutation that made it (None for a body of the initial population) and the
    policy weights."""

    type: Literal["FitnessReport"] = "FitnessReport"
    child: Id
    job: Id
    node: Id
    genome: Genome
    mutation: str | None = None
    mutation_detail: Text = ""
    fitness: Finite
    fitness_source: FitnessSource
    fitness_episodes: Count
    curve: Curve
    energy: Measure
    cost_of_work: Measure
    mass: Positive
    episodes: Count
    env_steps: Count
    wall_s: NonNegative
    steps_per_s: NonNegative
    checkpoint: Annotated[bytes, Field(strict=True, max_length=MAX_CHECKPOINT_BYTES)]
    """`derl.rl.checkpoint.Checkpoint.to_bytes()` of the trained policy."""

    @field_validator("mutation")
    @classmethod
    def _known_operator(cls, value: str | None) -> str | None:
        if value is not None and value not in OPERATORS:
            raise ValueError(f"unknown mutation operator {value!r}; known: {', '.join(OPERATORS)}")
        return value


class Ack(MessageBase):
    """The coordinator's acknowledgement of a FitnessReport or an EvalResult sent by `node`."""

    type: Literal["Ack"] = "Ack"
    of: Literal["FitnessReport", "EvalResult"]
    job: Id
    child: Id
    node: Id


class EvalResult(MessageBase):
    """An evaluator's result for one agent in one test task, trained `steps` env steps with
    `seed` (the budget matters: the paper reports 5M- and 1M-step evaluations)."""

    type: Literal["EvalResult"] = "EvalResult"
    agent: Id
    task: Id
    seed: Seed
    steps: Steps
    reward: Finite
    cost_of_work: Measure
    curve: Curve
    node: Id
    job: Id


class Reject(MessageBase):
    """The coordinator's refusal of a FitnessReport or an EvalResult that `node` sent for `job`:
    it will never be accepted (`reason`), so the sender drops it and asks for work again."""

    type: Literal["Reject"] = "Reject"
    of: Literal["FitnessReport", "EvalResult"]
    job: Id
    child: Id
    node: Id
    reason: Text


class Cancel(MessageBase):
    """The coordinator's order to `node` to stop `job`: its result is no longer wanted (another
    worker's report for the same child was accepted first)."""

    type: Literal["Cancel"] = "Cancel"
    job: Id
    node: Id
    reason: Text


class JobLost(MessageBase):
    """A fact of the coordinator: `job` was taken back from `node` (its liveliness token
    vanished, or it sent no progress for its lease); its subject waits for the next worker. A
    report for it that arrives before the subject is done still counts."""

    type: Literal["JobLost"] = "JobLost"
    job: Id
    node: Id
    reason: Text


class JobFailed(MessageBase):
    """A worker's report that `job` failed: what failed and the exception's text. The worker
    then asks for work again; the coordinator retries the subject up to `max_attempts` times."""

    type: Literal["JobFailed"] = "JobFailed"
    job: Id
    node: Id
    subject: Id
    error: Text


class Birth(MessageBase):
    """A child born: the authoritative birth stream, published on ``births/<child>`` once the
    coordinator has journaled it. `birth` is the birth index (0 first), `generation` the parent's
    plus one (0 for the initial population); `node` trained it (for a repeat: the node that
    trained the earlier body, `repeat_of`, whose result the child takes)."""

    type: Literal["Birth"] = "Birth"
    child: Id
    parent: Id | None = None
    job: Id
    node: Id
    birth: Count
    generation: Count
    fitness: Finite
    cost_of_work: Measure
    energy: Measure
    mass: Positive
    mutation: str | None = None
    mutation_detail: Text = ""
    genome: Genome
    repeat_of: Id | None = None


class ChildFailed(MessageBase):
    """A child given up after `attempts` failed trainings (also on ``births/<child>``): it is
    never born, and the run goes on without it."""

    type: Literal["ChildFailed"] = "ChildFailed"
    child: Id
    parent: Id | None = None
    attempts: Count
    error: Text


class Rejection(MessageBase):
    """A fact of the coordinator: a message it refused (`reason`), from `sender` on `key`."""

    type: Literal["Rejection"] = "Rejection"
    reason: Text
    key: Text
    sender: Id | None = None
    of: Text = ""
    job: Id | None = None


class PopulationSnapshot(MessageBase):
    """The current population (periodic and on change); `birth_counter` births so far."""

    type: Literal["PopulationSnapshot"] = "PopulationSnapshot"
    birth_counter: Count
    members: Annotated[tuple[Member, ...], Field(max_length=MAX_ITEMS)] = ()

    @model_validator(mode="after")
    def _consistent(self) -> PopulationSnapshot:
        agents = [m.agent for m in self.members]
        if len(set(agents)) != len(agents):
            raise ValueError("an agent appears twice")
        late = [m.agent for m in self.members if m.birth >= self.birth_counter]
        if late:
            raise ValueError(f"birth index >= birth_counter {self.birth_counter} for {late[:5]}")
        return self


class RunStatus(MessageBase):
    """Counts and the best agent so far (both None before the first birth): `born` children
    (`repeats` of them were repeats of an earlier body), `failed` children given up, `rejected`
    messages, `in_flight` jobs."""

    type: Literal["RunStatus"] = "RunStatus"
    born: Count
    target: Steps
    best_fitness: Finite | None = None
    best_agent: Id | None = None
    in_flight: Count
    workers_alive: Count
    evaluated: Count = 0
    eval_target: Count = 0
    failed: Count = 0
    repeats: Count = 0
    rejected: Count = 0
    steps_per_s: NonNegative = 0.0
    done: bool = False

    @model_validator(mode="after")
    def _best_complete(self) -> RunStatus:
        if (self.best_fitness is None) != (self.best_agent is None):
            raise ValueError("best_fitness and best_agent are given together or not at all")
        return self


Message = Annotated[
    WorkerReady
    | TrainJob
    | EvalJob
    | Tournament
    | TrainProgress
    | FitnessReport
    | Ack
    | EvalResult
    | Reject
    | Cancel
    | JobLost
    | JobFailed
    | Birth
    | ChildFailed
    | Rejection
    | PopulationSnapshot
    | RunStatus,
    Field(discriminator="type"),
]
"""Any message; validating against it dispatches on `type`."""

MESSAGE_TYPES: Final[dict[str, type[MessageBase]]] = {
    cls.__name__: cls for cls in get_args(get_args(Message)[0])
}
"""Message class by type name."""
