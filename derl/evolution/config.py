"""One evolution run's settings: the paper's, and small profiles that finish on one machine.

A profile is a pydantic model (unknown keys are errors), built in (`smoke`, `demo`, `paper`) or
read from a YAML file whose keys are this model's fields (``profile: demo`` in the file starts
from a built-in profile and overrides the rest); a command's ``--set KEY=VALUE`` changes one
setting more (`load_settings`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    JsonValue,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from derl.envs.batched import EnvConfig
from derl.envs.registry import TASK_REGISTRY, TEST_TASKS, make_task
from derl.evolution.selection import SELECTION_REGISTRY, make_selection
from derl.evolution.timing import TrainingTime
from derl.lifetime import ppo_config
from derl.plugins import Plugin, Registry, canonical
from derl.rl import PPOConfig, PPOHyperparameters
from derl.rl.config import SAVED
from derl.unimal.mutations import OPERATOR_REGISTRY
from derl.validation import problems

SEED_LIMIT = 2**64  # seeds travel as unsigned 64-bit integers
MAX_LEASE_S = 86_400.0

Settings = TypeVar("Settings", bound=BaseModel)


class JobSettings(BaseModel):
    """What every coordinator's settings share (`EvolutionConfig`, a study's `StudyConfig`): the
    profile's name, how each training learns (`num_envs`, `ppo`: `job_ppo`) and how its jobs are
    leased and retried."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field("custom", description="the profile's name (a file's: its stem)")
    num_envs: int = Field(32, ge=1, description="environment copies of every training")
    ppo: PPOHyperparameters = Field(
        default_factory=PPOHyperparameters, description="PPO hyperparameters"
    )
    lease_s: float = Field(
        60.0, gt=0, le=MAX_LEASE_S, description="a job without progress this long is reassigned"
    )
    max_attempts: int = Field(
        3,
        ge=1,
        le=100,
        description="failed jobs of a training or an evaluation before it is given up",
    )

    def job_ppo(self, task: str, steps: int, seed: int) -> PPOConfig:
        """The PPO of one job: the hyperparameters with the job's budget, seed and copies and the
        task's fitness settings; ValueError saying why when the budget does not fit them."""
        try:
            return ppo_config(task, steps, seed, num_envs=self.num_envs, **self.ppo.model_dump())
        except ValidationError as error:
            raise ValueError(f"PPO of {task} with {steps} steps: {problems(error)}") from None


def setting_keys(model: type[BaseModel]) -> list[str]:
    """`model`'s keys in the order its reference and its errors list them: a coordinator's
    settings (a `JobSettings`) their name, their own keys, then the ones every coordinator shares;
    any other model its fields in order."""
    keys = list(model.model_fields)
    if not issubclass(model, JobSettings):
        return keys
    shared = list(JobSettings.model_fields)
    return [shared[0], *(k for k in keys if k not in shared), *shared[1:]]


class EvolutionConfig(JobSettings):
    """Population, tournaments, budget and lifetime learning of one run: the whole configuration
    of a run, checked before anything starts and saved with it (`profile.json`), so a resumed run
    trains exactly as it started. `ppo` holds the PPO hyperparameters; each job's budget, seed,
    copies and fitness settings come from `train_steps`, `training_seed`, `num_envs` and the task
    (`training_ppo`, `evaluation_ppo`)."""

    world: str = Field(
        "ft",
        description="the world evolution trains in: ft, vt, mvt, a task of an installed plugin, "
        "or package.module:name (docs/extending.md)",
    )
    population: int = Field(576, ge=1, description="P: the aging window (most recent births)")
    tournament: int = Field(4, ge=1, description="T: contestants drawn with replacement")
    selection: str = Field(
        "tournament",
        description="how a tournament picks its parent: tournament (the paper's: the fittest of "
        "T), pareto (among T, one not beaten on both fitness and cost of work), a scheme of an "
        "installed plugin, or package.module:name",
    )
    selection_options: dict[str, JsonValue] = Field(
        default_factory=dict, description="keyword options of the selection scheme's factory"
    )
    mutations: dict[str, float] | None = Field(
        None,
        description="the mutation operators and their weights (a child's operator is drawn in "
        "proportion among those that apply; a plugin's by name or package.module:name); None: "
        "the paper's uniform choice among the seven built-ins",
    )
    total: int = Field(4000, ge=1, description="N: bodies trained in all, initial ones included")
    in_flight: int = Field(
        288,
        ge=0,
        description="W: children in flight: child n is bred from the P latest born of the first "
        "n - W children (the paper's 288 trainings at once), so the run is the same whatever the "
        "number of trainers (keep W at 2-4x the trainers); 0: free-running, the P most recently "
        "born (not reproducible)",
    )
    timing: Literal["window", "cluster"] = Field(
        "window",
        description="how the population a child is bred from follows the trainings' times: "
        "window: child n from the first n - W children, whatever their times (timing-free); "
        "cluster: the released code's W workers simulated in virtual time, each breeding a child "
        "when its training ends from the P bodies that finished last, so bodies that train fast "
        "join sooner (durations from `training_time`); both are the same on any number of "
        'trainers (docs/fidelity.md, "Timing")',
    )
    end: Literal["all", "released"] = Field(
        "all",
        description="how the run ends: all: every one of the N children is trained and born; "
        "released (timing cluster only): as the released code, whose workers breed until N "
        "bodies are saved and drop what is in flight then: the virtual workers breed while "
        "fewer than N bodies finished, and the run keeps the N that finished first "
        '(docs/fidelity.md, "End of a run")',
    )
    training_time: TrainingTime = Field(
        default_factory=TrainingTime,
        description="the cluster timing's virtual duration of a training, from its counts",
    )
    audit: float = Field(
        0.02,
        ge=0,
        le=1,
        description="the share of children trained twice, by two trainer identities, whose "
        "results must agree bit for bit (a third training decides a disagreement and the "
        "identity that lied is quarantined); 0: none. Trainers must be one machine type with "
        "one set of library versions (training is deterministic only there)",
    )
    audit_first: int = Field(
        1,
        ge=0,
        description="where audit > 0: every report of a trainer identity is audited until this "
        "many of them agreed with another identity's (again after a disagreement it was part "
        "of); then a share (audit_first / (n + 1))² of its reports, n its reports taken since "
        '(docs/running.md, "Audits")',
    )
    audit_top: float = Field(
        0.03,
        ge=0,
        le=1,
        description="where audit > 0: a child whose reported fitness ranks among this share of "
        "the best of the population is audited before it is born (a likely parent)",
    )
    inherit: Literal["none", "parent"] = Field(
        "none",
        description="where a child's controller starts: none, fresh weights (the paper: every "
        "child trained from scratch); parent, its parent's trained weights where the two bodies' "
        "parts match, fresh ones where they do not (Lamarckian; docs/extending.md)",
    )
    train_steps: int = Field(
        5_000_000,
        ge=1,
        description="PPO env steps per body, rounded down to whole rollouts (num_envs × "
        "ppo.rollout_steps), as the released code does",
    )
    released_delete_limb: bool = Field(
        True,
        description="as the released mutate_delete_limb: a child that lost a limb keeps its "
        "parent's stand height (spawn height and fall threshold); false: its own (corrected)",
    )
    training_seed: int = Field(
        1409, ge=0, lt=SEED_LIMIT, description="the same for every lifetime (the paper's)"
    )
    seed: int = Field(
        0, ge=0, lt=SEED_LIMIT, description="seeds the initial bodies and the tournaments"
    )
    eval_top: int = Field(0, ge=0, description="best bodies evaluated on the test tasks at the end")
    eval_tasks: tuple[str, ...] = Field((), description="test tasks of the final evaluations")
    eval_seeds: int = Field(1, ge=1, description="evaluations of each body per test task (seeds)")
    eval_steps: int = Field(1_000_000, ge=1, description="PPO env steps per evaluation")

    def training_ppo(self) -> PPOConfig:
        """The PPO of every training of this run's evolution."""
        return self.job_ppo(self.world, self.train_steps, self.training_seed)

    def evaluation_ppo(self, task: str, seed: int) -> PPOConfig:
        """The PPO of one test-task evaluation."""
        return self.job_ppo(task, self.eval_steps, seed)

    def fitness_bound(self) -> float:
        """The largest |fitness| the world allows, derived from its reward terms' own bounds
        (`derl.envs.task.Task.fitness_bound`): a report beyond it is impossible."""
        return EnvConfig().fitness_bound(make_task(self.world))

    @model_validator(mode="before")
    @classmethod
    def _as_saved_before(cls, data: object, info: ValidationInfo) -> object:
        """A run saved before `in_flight` existed (2026-12-04) was free-running, and one saved
        before `audit` (2026-12-05) checked nothing, one saved before `audit_first` and
        `audit_top` (2026-12-07) audited by its share alone: it resumes so."""
        if info.context == SAVED and isinstance(data, dict):
            return {"in_flight": 0, "audit": 0.0, "audit_first": 0, "audit_top": 0.0, **data}
        return data

    @field_validator("world", "selection")
    @classmethod
    def _canonical_name(cls, value: str) -> str:
        """A spec's ``module:name`` kept as ``module.name`` (a safe name on the bus)."""
        return canonical(value)

    @field_validator("eval_tasks")
    @classmethod
    def _canonical_tasks(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(canonical(task) for task in value)

    @field_validator("mutations")
    @classmethod
    def _canonical_operators(cls, value: dict[str, float] | None) -> dict[str, float] | None:
        if value is None:
            return None
        if any(weight < 0 or not math.isfinite(weight) for weight in value.values()):
            raise ValueError(f"mutation weights must be finite and >= 0: {value}")
        if not any(value.values()):
            raise ValueError("mutations: at least one operator needs a positive weight")
        return {canonical(op): weight for op, weight in value.items()}

    def plugins(self) -> tuple[Plugin, ...]:
        """The identities of the plugins this profile names (world, test tasks, selection,
        operators), in that order: what every job carries and the fingerprint covers."""
        named: list[tuple[Registry[Any], str]] = [
            (TASK_REGISTRY, self.world),
            *((TASK_REGISTRY, task) for task in self.eval_tasks),
            (SELECTION_REGISTRY, self.selection),
            *((OPERATOR_REGISTRY, op) for op in self.mutations or {}),
        ]
        found = (registry.identity(name) for registry, name in named)
        return tuple(dict.fromkeys(plugin for plugin in found if plugin is not None))

    @model_validator(mode="after")
    def _consistent(self) -> EvolutionConfig:
        for task in (self.world, *self.eval_tasks):
            TASK_REGISTRY.get(task)  # a PluginError (a ValueError) says why not
        make_selection(self.selection, self.selection_options)
        for op in self.mutations or {}:
            OPERATOR_REGISTRY.get(op)
        if self.total < self.population:
            raise ValueError(f"total ({self.total}) < population ({self.population})")
        if self.tournament > self.population:
            raise ValueError(
                f"tournament ({self.tournament}) > population ({self.population}): a tournament "
                "draws T of the P most recent births"
            )
        if self.in_flight >= self.population:
            raise ValueError(
                f"in_flight ({self.in_flight}) >= population ({self.population}): child n is bred "
                "from the first n - W children, so W must be less than P"
            )
        if self.timing == "cluster" and not self.in_flight:
            raise ValueError("timing cluster needs its W workers: in_flight >= 1")
        if self.end == "released" and self.timing != "cluster":
            raise ValueError("end released needs timing cluster: its virtual finishes decide "
                             "which N bodies the run keeps")  # fmt: skip
        if self.eval_top and not self.eval_tasks:
            raise ValueError("eval_top needs eval_tasks")
        self.training_ppo()  # the budget holds whole rollouts, the minibatch fits, ...
        for task in self.eval_tasks:
            self.evaluation_ppo(task, 0)
        return self


PROFILES: dict[str, EvolutionConfig] = {
    "smoke": EvolutionConfig(
        name="smoke",
        population=4,
        tournament=2,
        total=8,
        in_flight=2,
        audit=0.0,
        train_steps=8192,
        num_envs=16,
        lease_s=30.0,
        eval_top=1,
        eval_tasks=("patrol", "incline"),
        eval_steps=4096,
    ),
    "demo": EvolutionConfig(
        name="demo",
        population=16,
        tournament=4,
        total=128,
        in_flight=8,
        audit=0.05,
        train_steps=250_000,
        eval_top=2,
        eval_tasks=TEST_TASKS,
        eval_steps=100_000,
    ),
    "paper": EvolutionConfig(
        name="paper", timing="cluster", eval_top=10, eval_tasks=TEST_TASKS, eval_seeds=5
    ),
}


class NoProfile(ValueError):
    """A profile named that is neither built in nor a file."""


def load_profile(
    name_or_path: str, changes: Iterable[tuple[str, object]] = (), **overrides: object
) -> EvolutionConfig:
    """A built-in profile by name, or a YAML file, with `changes` (dotted key, value) made to
    it; `overrides` (e.g. world) win."""
    return load_settings(EvolutionConfig, PROFILES, name_or_path, changes, **overrides)


def load_settings(
    model: type[Settings],
    builtin: dict[str, Settings],
    name_or_path: str,
    changes: Iterable[tuple[str, object]] = (),
    **overrides: object,
) -> Settings:
    """One of `builtin` by name, or a YAML file of `model`'s fields (``profile: NAME`` in it
    starts from a built-in one, its name is the file's stem), then each of `changes`: a value
    set at a dotted key (``ppo.lr``), validated with the rest; `overrides` that are set win."""
    if name_or_path in builtin:
        base: dict[str, object] = builtin[name_or_path].model_dump()
    else:
        path = Path(name_or_path)
        if not path.is_file():
            raise NoProfile(f"no profile {name_or_path!r}: use {', '.join(builtin)} or a YAML file")
        data = yaml.safe_load(path.read_text())
        if data is None:  # an empty file would silently be a run with every default
            raise ValueError(
                f"the file holds no settings: start it with `profile: NAME` ({', '.join(builtin)}) "
                "and add the keys to change"
            )
        if not isinstance(data, dict):
            raise ValueError("a profile is a mapping of settings")
        parent = data.pop("profile", None)
        if parent is not None and (not isinstance(parent, str) or parent not in builtin):
            raise ValueError(
                f"`profile: {parent}` is not a built-in profile; choose {', '.join(builtin)}"
            )
        base = {**(builtin[parent].model_dump() if parent else {}), "name": path.stem, **data}
    for key, value in changes:
        set_dotted(base, key, value)
    chosen = {k: v for k, v in overrides.items() if v is not None}
    return model.model_validate({**base, **chosen})


def set_dotted(settings: dict[str, object], key: str, value: object) -> None:
    """Set `value` at the dotted `key` of nested `settings` (a key that is not a field is left
    for validation to name); ValueError when a part of the path holds a single value."""
    *groups, last = key.split(".")
    inner = settings
    for depth, part in enumerate(groups):
        group = inner.setdefault(part, {})
        if not isinstance(group, dict):
            path = ".".join(groups[: depth + 1])
            raise ValueError(f"cannot set {key}: {path} is one value, not a group of settings")
        inner = group
    inner[last] = value
