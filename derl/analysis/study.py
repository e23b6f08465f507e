"""A study's settings: the paper's reporting method (appendix D) over finished evolution runs.

A study takes the runs of one or more worlds (the paper: 3 per world, with different seeds),
retrains the `per_lineage` fittest bodies of every surviving lineage with `seeds` new seeds in
their own world, keeps each world's `keep` best by mean fitness (the paper's 100, the data of
figs. 2a, 5a, 5c and 6), and trains the `top` best of those from scratch on every test task with
`test_seeds` seeds at each of the `budgets` (fig. 4b: 5M env steps, fig. 4c: 1M). Profiles work as
evolution's: built in (`smoke`, `demo`, `paper`) or a YAML file of these fields (``profile:``
starts from a built-in one).
"""

from __future__ import annotations

from collections.abc import Iterable

from pydantic import Field, field_validator, model_validator

from derl.envs.registry import TASK_REGISTRY, TEST_TASKS, WORLDS
from derl.evolution.config import JobSettings, load_settings
from derl.plugins import canonical


class StudyConfig(JobSettings):
    """Appendix D's numbers and the learning settings of its trainings (the paper: the same as
    evolution's; `JobSettings` holds them)."""

    per_lineage: int = Field(3, ge=1, description="fittest bodies retrained per surviving lineage")
    seeds: int = Field(5, ge=1, description="new training seeds of each retrained body")
    seed: int = Field(0, ge=0, description="draws the new seeds")
    retrain_steps: int | None = Field(
        None, ge=1, description="env steps of a retraining (None: its run's lifetime budget)"
    )
    keep: int = Field(100, ge=1, description="best bodies per world by mean retrained fitness")
    top: int = Field(10, ge=1, description="of those, the best tested on the test tasks")
    test_tasks: tuple[str, ...] = Field(
        TEST_TASKS, min_length=1, description="the test tasks (built-in, or a plugin's)"
    )

    @field_validator("test_tasks")
    @classmethod
    def _canonical_tasks(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(canonical(task) for task in value)

    test_seeds: int = Field(5, ge=1, description="trainings of each tested body per task")
    budgets: tuple[int, ...] = Field(
        (5_000_000, 1_000_000), min_length=1, description="env steps of a test (figs. 4b, 4c)"
    )

    @model_validator(mode="after")
    def _consistent(self) -> StudyConfig:
        for task in self.test_tasks:
            TASK_REGISTRY.get(task)  # a PluginError (a ValueError) says why not
        if self.top > self.keep:
            raise ValueError(f"top ({self.top}) > keep ({self.keep}): the tested are kept ones")
        if len(set(self.budgets)) != len(self.budgets):
            raise ValueError(f"budgets {self.budgets} repeat one")
        for task in self.test_tasks:  # each budget holds whole rollouts, the minibatch fits ...
            for steps in self.budgets:
                self.job_ppo(task, steps, 0)
        if self.retrain_steps is not None:
            for world in WORLDS:
                self.job_ppo(world, self.retrain_steps, 0)
        return self


STUDY_PROFILES: dict[str, StudyConfig] = {
    "smoke": StudyConfig(
        name="smoke",
        per_lineage=1,
        seeds=2,
        retrain_steps=4096,
        keep=2,
        top=1,
        test_tasks=("patrol", "incline"),
        test_seeds=1,
        budgets=(4096, 2048),
        num_envs=16,
        lease_s=30.0,
    ),
    "demo": StudyConfig(
        name="demo",
        seeds=3,
        keep=20,
        top=4,
        test_seeds=2,
        budgets=(300_000, 100_000),
    ),
    "paper": StudyConfig(name="paper"),
}


def load_study_profile(
    name_or_path: str, changes: Iterable[tuple[str, object]] = ()
) -> StudyConfig:
    """A built-in study profile by name, or a YAML file of `StudyConfig` fields, with `changes`
    (dotted key, value) made to it."""
    return load_settings(StudyConfig, STUDY_PROFILES, name_or_path, changes)
