"""The message models of the bus (docs/architecture.md), one frozen pydantic model per type.

Every message carries `schema_version`, its `type` (the discriminator, equal to the class name)
and the `run` it belongs to. Unknown fields and out-of-range values are validation errors. Ids
are the same throughout: `node` a worker, `job` one assignment, `child`/`agent` a body, `parent`
the body it was mutated from (None for the initial population).
"""

from __future__ import annotations

from typing import Annotated, Final, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

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

SCHEMA_VERSION: Final = 2

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
    """The coordinator's order to `node`: train `child` from scratch in `task`.

    The child's body is `genome`, or, when `mutation_seed` is set (a tournament's child not yet
    born), `derl.evolution.breed(genome, mutation_seed)`: `genome` is then the parent's body and
    the trainer breeds the child itself (deterministic: every attempt gets the same body).
    """

    type: Literal["TrainJob"] = "TrainJob"
    job: Id
    child: Id
    node: Id
    genome: Genome
    task: Id
    steps: Steps
    seed: Seed
    parent: Id | None = None
    mutation_seed: Seed | None = None
    lease_s: LeaseSeconds
    num_envs: Annotated[int, Field(ge=1, le=65_536)] = 32

    @model_validator(mode="after")
    def _bred_from_parent(self) -> TrainJob:
        if self.mutation_seed is not None and self.parent is None:
            raise ValueError("a mutation_seed needs the parent it mutates")
        return self


class EvalJob(MessageBase):
    """The coordinator's order to `node`: train and evaluate `agent`'s body in an eval task."""

    type: Literal["EvalJob"] = "EvalJob"
    job: Id
    agent: Id
    node: Id
    genome: Genome
    task: Id
    seed: Seed
    steps: Steps
    lease_s: LeaseSeconds
    num_envs: Annotated[int, Field(ge=1, le=65_536)] = 32


class Tournament(MessageBase):
    """A decision, recorded as a fact: the contestants, the winner (parent) and the seed of the
    child's mutation (`derl.evolution.breed`; its FitnessReport names the mutation).

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
    def _parent_is_fittest(self) -> Tournament:
        if len(self.contestants) != len(self.fitness):
            raise ValueError(
                f"{len(self.contestants)} contestants but {len(self.fitness)} fitness values"
            )
        best = max(self.fitness)
        winners = {c for c, f in zip(self.contestants, self.fitness, strict=True) if f == best}
        if self.parent not in winners:
            raise ValueError(f"parent {self.parent!r} is not a fittest contestant")
        if self.child in self.contestants:
            raise ValueError(f"child {self.child!r} is among the contestants")
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
    """An evaluator's result for one agent in one evaluation task."""

    type: Literal["EvalResult"] = "EvalResult"
    agent: Id
    task: Id
    seed: Seed
    reward: Finite
    cost_of_work: Measure
    curve: Curve
    node: Id
    job: Id


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
    """Counts and the best agent so far (both None before the first birth)."""

    type: Literal["RunStatus"] = "RunStatus"
    born: Count
    target: Steps
    best_fitness: Finite | None = None
    best_agent: Id | None = None
    in_flight: Count
    workers_alive: Count
    evaluated: Count = 0
    eval_target: Count = 0
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
    | PopulationSnapshot
    | RunStatus,
    Field(discriminator="type"),
]
"""Any message; validating against it dispatches on `type`."""

MESSAGE_TYPES: Final[dict[str, type[MessageBase]]] = {
    cls.__name__: cls for cls in get_args(get_args(Message)[0])
}
"""Message class by type name."""
