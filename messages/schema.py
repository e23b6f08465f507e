"""The message models of the bus (docs/architecture.md), one frozen pydantic model per type.

Every message carries `schema_version`, its `type` (the discriminator, equal to the class name)
and the `run` it belongs to. Unknown fields and out-of-range values are validation errors. Ids
are the same throughout, one name each (docs/architecture.md, "Glossary"): `node` a worker, `job`
one assignment, `agent` a body with its controller (a child before it is born, a member of the
population after), `parent` the agent it was mutated from (None for the initial population).
"""

from __future__ import annotations

from typing import Annotated, Final, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, model_validator

from derl.messages.types import (
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
from derl.plugins import Plugin
from derl.rl.config import PPOConfig
from derl.unimal.genome import Genome
from derl.unimal.space import OPERATOR_NAMES

SCHEMA_VERSION: Final = 5

SCHEMA_CHANGES: Final = {
    4: "the coordinator decides every body: a `TrainJob` carries the child's own body and the "
    "mutation that made it (`mutation`, `mutation_detail`) instead of its parent's body and a "
    "`mutation_seed`, and a `FitnessReport` names no mutation (its body must be its job's)",
    5: "one name per id: the agent a message is about is `agent` in every message (it was `child` "
    "in Tournament, TrainJob, TrainProgress, FitnessReport, Ack, Reject, Birth, ChildFailed, "
    "Quarantine and Retrained, and `subject` in JobFailed), and the keys' id segment is "
    "`<agent>`; `derl log upgrade` brings a version-4 journal or recording to it",
}
"""What each schema version changed from the one before."""

FitnessSource = Literal["window", "last_episodes", "unfinished"]
"""As `derl.rl.episodes.FitnessSource`: "window" (the learning curve's values of the iterations in
the last window of steps, the definition), "last_episodes" (a single episode finished: its sum),
"unfinished" (none did: the partial sums of the running episodes)."""

LeaseSeconds = Annotated[float, Field(gt=0, le=86_400, allow_inf_nan=False)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)


class MessageBase(_Model):
    """What every message carries."""

    schema_version: Literal[5] = SCHEMA_VERSION  # SCHEMA_VERSION (mypy checks they agree)
    """The wire format's version; a payload of another version is refused."""
    type: str
    """The message type: the model's class name (the discriminator)."""
    run: Id
    """The run the message belongs to (also the key's second segment)."""


class Curve(_Model):
    """A learning curve: mean return after each number of env steps (steps never decrease)."""

    env_steps: Annotated[tuple[Count, ...], Field(max_length=MAX_ITEMS)] = ()
    """Env steps (all copies) done at each point."""
    returns: Annotated[tuple[Finite, ...], Field(max_length=MAX_ITEMS)] = ()
    """Mean return of the recent episodes at each point."""

    @model_validator(mode="after")
    def _aligned(self) -> Curve:
        if len(self.env_steps) != len(self.returns):
            raise ValueError(
                f"{len(self.env_steps)} env_steps but {len(self.returns)} returns: one each"
            )
        if any(a > b for a, b in zip(self.env_steps, self.env_steps[1:], strict=False)):
            raise ValueError("env_steps must not decrease")
        return self


class PopulationEntry(_Model):
    """One agent of the population, as a snapshot lists it."""

    agent: Id
    """The agent's id."""
    fitness: Finite
    """Its fitness."""
    parent: Id | None = None
    """The body it was mutated from (None in the initial population)."""
    birth: Count
    """Its birth index (0 first)."""


class WorkerReady(MessageBase):
    """An idle trainer or evaluator asking for work (repeated until it gets some)."""

    type: Literal["WorkerReady"] = "WorkerReady"
    node: Id
    """The worker's node id."""
    role: Literal["trainer", "evaluator"]
    """What work it takes."""
    host: Annotated[str, Field(min_length=1, max_length=253)]
    """Its host name."""
    pid: Annotated[int, Field(ge=1, le=2**32)]
    """Its process id."""
    nthread: Annotated[int, Field(ge=1, le=4096)] = 1
    """Simulation threads it runs."""


class ParentWeights(_Model):
    """The trained controller a child starts from where the run inherits (`inherit: parent`):
    its parent's, the file the coordinator answers a query on `checkpoint/<parent>` from."""

    genome: Genome
    """The parent's body (what its weights are of)."""
    sha256: Annotated[bytes, Field(strict=True, min_length=32, max_length=32)]
    """SHA-256 of the parent's checkpoint: the trainer trains only from bytes that have it."""


class TrainJob(MessageBase):
    """The coordinator's order to `node`: train `agent`, whose body is `genome`, from scratch in
    `task` with `ppo`.

    The coordinator decides every body: an initial one is drawn from the run's seed, a
    tournament's child is bred by the coordinator from its parent's body (`mutation` says how),
    and a report of another body is rejected. `ppo` is the whole learning configuration (budget,
    seed, copies, hyperparameters), as saved with the run, so a resumed run trains as it started
    whatever the code's defaults are now.
    """

    type: Literal["TrainJob"] = "TrainJob"
    job: Id
    """The assignment's id (a new one for every attempt)."""
    agent: Id
    """The child to train."""
    node: Id
    """The trainer it is assigned to."""
    genome: Genome
    """The child's body."""
    task: Id
    """The world to train in (ft, vt or mvt)."""
    ppo: PPOConfig
    """The whole learning configuration: budget, seed, copies, hyperparameters."""
    parent: Id | None = None
    """The body the child is mutated from (None in the initial population)."""
    mutation: str | None = None
    """The mutation operator that made the child from its parent (None in the initial
    population)."""
    mutation_detail: Text = ""
    """What the mutation changed, in words."""
    lease_s: LeaseSeconds
    """Seconds without progress after which the job is taken back."""
    inherit: ParentWeights | None = None
    """The parent's trained controller the child's starts from (`inherit: parent`: where their
    parts match); None: from scratch."""
    plugins: tuple[Plugin, ...] = ()
    """Every plugin the run's profile names (docs/extending.md): a node that lacks one or holds
    another version refuses the job (`JobRefused`)."""

    @property
    def steps(self) -> int:
        return self.ppo.total_steps

    @property
    def seed(self) -> int:
        return self.ppo.seed

    @model_validator(mode="after")
    def _mutated_from_parent(self) -> TrainJob:
        operators = {p.name for p in self.plugins if p.kind == "operator"}
        if self.mutation is not None and self.mutation not in {*OPERATOR_NAMES, *operators}:
            known = ", ".join([*OPERATOR_NAMES, *sorted(operators)])
            raise ValueError(f"unknown mutation operator {self.mutation!r}; known: {known}")
        if (self.mutation is None) != (self.parent is None):
            raise ValueError("a child has a parent and the mutation that made it, or neither")
        if self.inherit is not None and self.parent is None:
            raise ValueError("a child inherits its parent's weights: it needs a parent")
        return self


class EvalJob(MessageBase):
    """The coordinator's order to `node`: train `agent`'s body from scratch in a test task with
    `ppo` (its budget and seed) and report the score."""

    type: Literal["EvalJob"] = "EvalJob"
    job: Id
    """The assignment's id."""
    agent: Id
    """The evolved agent whose body is evaluated."""
    node: Id
    """The evaluator it is assigned to."""
    genome: Genome
    """The agent's body."""
    task: Id
    """The test task."""
    ppo: PPOConfig
    """The learning configuration of the evaluation (its budget and seed)."""
    lease_s: LeaseSeconds
    """Seconds without progress after which the job is taken back."""
    plugins: tuple[Plugin, ...] = ()
    """As in `TrainJob`."""

    @property
    def steps(self) -> int:
        return self.ppo.total_steps

    @property
    def seed(self) -> int:
        return self.ppo.seed


class Tournament(MessageBase):
    """A decision, recorded as a fact: the contestants, the winner (parent) and the seed of the
    child's mutation (the coordinator breeds the child with `derl.evolution.breed`; its TrainJob
    carries the body and names the mutation). The rule that made it is
    `derl.evolution.Evolution.tournament`; the wire only carries the outcome.

    `iteration` counts the tournaments of the run (0 for the first).
    """

    type: Literal["Tournament"] = "Tournament"
    agent: Id
    """The child the winner begets."""
    contestants: Annotated[tuple[Id, ...], Field(min_length=1, max_length=10_000)]
    """The agents drawn, with replacement."""
    fitness: Annotated[tuple[Finite, ...], Field(min_length=1, max_length=10_000)]
    """Each contestant's fitness, in the same order."""
    parent: Id
    """The winner."""
    mutation_seed: Seed
    """Seed of the child's mutation."""
    iteration: Count
    """The tournament's index in the run (0 first)."""

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
    agent: Id
    """The agent being trained (a child, or the agent of an evaluation)."""
    job: Id
    """The job in progress."""
    node: Id
    """The worker doing it."""
    env_steps: Count
    """Env steps done so far (all copies)."""
    total_steps: Steps
    """The job's budget of env steps."""
    recent_return: Finite | None = None
    """Mean return of the recent episodes (None before the first one ends)."""
    steps_per_s: NonNegative
    """Env steps per second of this training."""

    @model_validator(mode="after")
    def _within_budget(self) -> TrainProgress:
        if self.env_steps > self.total_steps:
            raise ValueError(f"env_steps {self.env_steps} > total_steps {self.total_steps}")
        return self


class FitnessReport(MessageBase):
    """The outcome of a training job, re-sent until acknowledged; carries the body that was
    trained (its job's: a report of another body is rejected) and the policy weights."""

    type: Literal["FitnessReport"] = "FitnessReport"
    agent: Id
    """The child trained."""
    job: Id
    """The job it answers."""
    node: Id
    """The trainer that did it."""
    genome: Genome
    """The body that was trained: its job's."""
    fitness: Finite
    """Mean episode sum of the world's selection term (the fitness)."""
    fitness_source: FitnessSource
    """Which episodes the fitness comes from."""
    fitness_episodes: Count
    """Finished episodes the fitness averages."""
    curve: Curve
    """The learning curve."""
    energy: Measure
    """Mean sum of |joint torque| per episode of the last ones (NaN: none finished)."""
    cost_of_work: Measure
    """Energy / (mass g reward) (NaN when the reward is not positive)."""
    mass: Positive
    """The body's mass, kg."""
    episodes: Count
    """Episodes finished in the training."""
    env_steps: Count
    """Env steps done (all copies)."""
    constraint_rows: Count = 0
    """MuJoCo's constraint rows (contacts, joint limits) at the end of each control step, summed
    over the copies and the steps: the deterministic cost measure of the cluster timing
    (`derl.evolution.timing`; 0 in journals from before it)."""
    wall_s: NonNegative
    """Wall-clock seconds of the training."""
    steps_per_s: NonNegative
    """Env steps per second of the training."""
    checkpoint: Annotated[bytes, Field(strict=True, max_length=MAX_CHECKPOINT_BYTES)]
    """`derl.rl.checkpoint.Checkpoint.to_bytes()` of the trained policy."""


class Ack(MessageBase):
    """The coordinator's acknowledgement of a FitnessReport or an EvalResult sent by `node`."""

    type: Literal["Ack"] = "Ack"
    of: Literal["FitnessReport", "EvalResult"]
    """The type of the report acknowledged."""
    job: Id
    """Its job."""
    agent: Id
    """What it is about (the child of a FitnessReport, the agent of an EvalResult)."""
    node: Id
    """The worker that sent it."""


class EvalResult(MessageBase):
    """An evaluator's result for one agent in one test task, trained `steps` env steps with
    `seed` (the budget matters: the paper reports 5M- and 1M-step evaluations)."""

    type: Literal["EvalResult"] = "EvalResult"
    agent: Id
    """The agent evaluated."""
    task: Id
    """The test task."""
    seed: Seed
    """The training seed."""
    steps: Steps
    """The budget of env steps."""
    reward: Finite
    """The task's fitness after training (as in FitnessReport)."""
    cost_of_work: Measure
    """As in FitnessReport (NaN when undefined)."""
    curve: Curve
    """The learning curve."""
    node: Id
    """The evaluator that did it."""
    job: Id
    """The job it answers."""


class Reject(MessageBase):
    """The coordinator's refusal of a FitnessReport or an EvalResult that `node` sent for `job`:
    it will never be accepted (`reason`), so the sender drops it and asks for work again."""

    type: Literal["Reject"] = "Reject"
    of: Literal["FitnessReport", "EvalResult"]
    """The type of the report refused."""
    job: Id
    """Its job."""
    agent: Id
    """What it is about (the child of a FitnessReport, the agent of an EvalResult)."""
    node: Id
    """The worker that sent it."""
    reason: Text
    """Why it is refused."""


class Cancel(MessageBase):
    """The coordinator's order to `node` to stop `job`: its result is no longer wanted (another
    worker's report for the same child was accepted first)."""

    type: Literal["Cancel"] = "Cancel"
    job: Id
    """The job to stop."""
    node: Id
    """The worker doing it."""
    reason: Text
    """Why."""


class JobLost(MessageBase):
    """A fact of the coordinator: `job` was taken back from `node` (its liveliness token
    vanished, or it sent no progress for its lease); its agent waits for the next worker. A
    report for it that arrives before the agent is done still counts."""

    type: Literal["JobLost"] = "JobLost"
    job: Id
    """The job taken back."""
    node: Id
    """The worker it was assigned to."""
    reason: Text
    """Why."""


class JobFailed(MessageBase):
    """A worker's report that `job` failed: what failed and the exception's text. The worker
    then asks for work again; the coordinator retries its agent up to `max_attempts` times. A
    worker that cannot run the run's jobs at all (`unfit`: it lacks one of the job's plugins or
    holds another version) refuses the job: that is no attempt of its agent, and the
    coordinator gives that worker no more jobs."""

    type: Literal["JobFailed"] = "JobFailed"
    job: Id
    """The job that failed."""
    node: Id
    """The worker that ran it."""
    agent: Id
    """The child trained or the agent evaluated."""
    error: Text
    """The exception's type and text."""
    unfit: bool = False
    """The worker refused the job: it cannot run any of the run's (`error` says why)."""


class Birth(MessageBase):
    """A child born: the authoritative birth stream, published on ``births/<agent>`` once the
    coordinator has journaled it. `birth` is the birth index (0 first), `generation` the parent's
    plus one (0 for the initial population); `node` trained it (for a repeat: the node that
    trained the earlier body, `repeat_of`, whose result the child takes)."""

    type: Literal["Birth"] = "Birth"
    agent: Id
    """The child born."""
    parent: Id | None = None
    """The body it was mutated from (None in the initial population)."""
    job: Id
    """The job whose report was accepted."""
    node: Id
    """The trainer that trained it (for a repeat: the one that trained the earlier body)."""
    birth: Count
    """The birth index (0 first)."""
    generation: Count
    """The parent's generation plus one (0 in the initial population)."""
    fitness: Finite
    """Its fitness."""
    cost_of_work: Measure
    """As in FitnessReport."""
    energy: Measure
    """As in FitnessReport."""
    mass: Positive
    """The body's mass, kg."""
    mutation: str | None = None
    """The mutation operator that made it (None in the initial population)."""
    mutation_detail: Text = ""
    """What the mutation changed, in words."""
    genome: Genome
    """The child's body."""
    episodes: Count = 0
    """As in FitnessReport (with `constraint_rows`: the training's cost in the cluster timing;
    0 in journals from before it)."""
    constraint_rows: Count = 0
    """As in FitnessReport."""
    repeat_of: Id | None = None
    """The earlier agent with the same body whose result it takes (None: trained)."""


class ChildFailed(MessageBase):
    """A child given up after `attempts` failed trainings (also on ``births/<agent>``): it is
    never born, and the run goes on without it."""

    type: Literal["ChildFailed"] = "ChildFailed"
    agent: Id
    """The child given up."""
    parent: Id | None = None
    """The body it was to be mutated from."""
    attempts: Count
    """Trainings that failed."""
    error: Text
    """The last error."""


class Quarantine(MessageBase):
    """A trainer identity caught lying (also on ``births/<agent>``, `agent` the child whose audit
    caught it): a third training of `agent` agreed with another identity's and not with its
    own. It gets no more jobs, its reports are rejected, and the children born from its reports
    that no audit checked (`retrain`) are trained again by others (`Retrained`)."""

    type: Literal["Quarantine"] = "Quarantine"
    node: Id
    """The identity (a worker's name without its ``.r<n>`` restart suffix)."""
    agent: Id
    """The child whose audit caught it."""
    jobs: Annotated[tuple[Id, ...], Field(max_length=100)]
    """The trainings of `agent` compared."""
    retrain: Annotated[tuple[Id, ...], Field(max_length=MAX_ITEMS)] = ()
    """Its unchecked births, trained again."""


class Undo(MessageBase):
    """A caught lie undone (also on ``births/<agent>``, `agent` the child whose audit caught
    `node`), once the liar's births are trained again: every tournament from `iteration` on was
    decided after the first of its births, while a lie was in the population, so each is void
    and decided again with the honest results. Their children (``c<iteration>`` on) are
    forgotten, born or not (their jobs cancelled); an honest training of a body bred again is
    kept: a child bred with it is born from it without training (its Birth names the kept job),
    so the run ends with the births of the same profile and seed run honestly."""

    type: Literal["Undo"] = "Undo"
    node: Id
    """The quarantined identity whose lie is undone."""
    agent: Id
    """The child whose audit caught it."""
    iteration: Count
    """The first tournament decided again."""
    voided: Count
    """Births forgotten."""


class Retrained(MessageBase):
    """A child born from a quarantined identity's report, trained again by another (also on
    ``births/<agent>``): its result replaces the one it was born with, for it and its repeats."""

    type: Literal["Retrained"] = "Retrained"
    agent: Id
    """The child."""
    job: Id
    """The job whose report replaces its result."""
    node: Id
    """The trainer that trained it again."""
    fitness: Finite
    """Its fitness."""
    was: Finite
    """The fitness it was born with (the quarantined identity's)."""
    cost_of_work: Measure
    """As in FitnessReport."""
    energy: Measure
    """As in FitnessReport."""
    mass: Positive
    """The body's mass, kg."""
    episodes: Count | None = None
    """Its training's episodes (the cluster timing's duration; None: not said)."""
    constraint_rows: Count | None = None
    """Its training's constraint rows, as in FitnessReport (None: not said)."""


class Dropped(MessageBase):
    """The released end of a run (`end: released`; also on ``births/<agent>``, `agent` the N-th
    body to finish in virtual time, the released run's last saved one): the children bred that
    are not among the N that finished first (in flight then, or trained past it) are dropped:
    their jobs are cancelled and a birth of theirs does not count."""

    type: Literal["Dropped"] = "Dropped"
    agent: Id
    """The N-th body to finish."""
    agents: Annotated[tuple[Id, ...], Field(max_length=MAX_ITEMS)]
    """The children dropped."""


class Rejection(MessageBase):
    """A fact of the coordinator: a message it refused (`reason`), from `sender` on `key`."""

    type: Literal["Rejection"] = "Rejection"
    reason: Text
    """Why it was refused."""
    key: Text
    """The key it came on."""
    sender: Id | None = None
    """The `node` it names, if any."""
    of: Text = ""
    """Its type."""
    job: Id | None = None
    """The `job` it names, if any."""


class RunSettings(MessageBase):
    """A fact of the coordinator: the settings the run goes on with (its profile, as JSON),
    journaled at its first start and again whenever they change (`derl run --extend` raising
    `total`): the journal says which settings made every birth."""

    type: Literal["RunSettings"] = "RunSettings"
    settings: Annotated[str, Field(max_length=65536)]
    """The profile, as JSON (docs/configuration.md)."""


class PopulationSnapshot(MessageBase):
    """The current population (periodic and on change); `birth_counter` birth numbers given."""

    type: Literal["PopulationSnapshot"] = "PopulationSnapshot"
    birth_counter: Count
    """Birth numbers given so far: the births, and those undone after a caught lie (whose
    numbers are not given again)."""
    members: Annotated[tuple[PopulationEntry, ...], Field(max_length=MAX_ITEMS)] = ()
    """The population: the most recent births."""

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
    """Children born."""
    target: Count
    """Children to be born in all (0 in a study: it trains no children)."""
    best_fitness: Finite | None = None
    """The best fitness so far."""
    best_agent: Id | None = None
    """The agent that has it."""
    in_flight: Count
    """Jobs assigned and not yet done."""
    workers_alive: Count
    """Trainers and evaluators alive."""
    evaluated: Count = 0
    """Evaluations done."""
    eval_target: Count = 0
    """Evaluations to do in all."""
    failed: Count = 0
    """Children given up."""
    repeats: Count = 0
    """Children born as repeats of an earlier body."""
    audited: Count = 0
    """Children born from two trainings that agreed bit for bit (`EvolutionConfig.audit`)."""
    quarantined: Annotated[tuple[Id, ...], Field(max_length=MAX_ITEMS)] = ()
    """Trainer identities caught lying (`Quarantine`)."""
    retraining: Count = 0
    """Children of quarantined identities still to be trained again."""
    rejected: Count = 0
    """Messages rejected."""
    steps_per_s: NonNegative = 0.0
    """Env steps per second: the sum of each worker's latest report."""
    done: bool = False
    """The run is finished."""

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
    | Quarantine
    | Retrained
    | Undo
    | Dropped
    | Rejection
    | RunSettings
    | PopulationSnapshot
    | RunStatus,
    Field(discriminator="type"),
]
"""Any message; validating against it dispatches on `type`."""

MESSAGE_TYPES: Final[dict[str, type[MessageBase]]] = {
    cls.__name__: cls for cls in get_args(get_args(Message)[0])
}
"""Message class by type name."""
