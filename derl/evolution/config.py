"""One evolution run's settings: the paper's, and small profiles that finish on one machine.

A profile is a pydantic model (unknown keys are errors), built in (`smoke`, `demo`, `paper`) or
read from a YAML file whose keys are this model's fields (``profile: demo`` in the file starts
from a built-in profile and overrides the rest).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from derl.envs.registry import TASKS


class EvolutionConfig(BaseModel):
    """Population, tournaments, budget and lifetime learning of one run."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = "custom"
    world: Literal["ft", "vt", "mvt"] = "ft"
    population: int = Field(576, ge=1, description="P: the aging window (most recent births)")
    tournament: int = Field(4, ge=1, description="T: contestants drawn with replacement")
    total: int = Field(4000, ge=1, description="N: bodies trained in all, initial ones included")
    train_steps: int = Field(5_000_000, ge=1, description="PPO env steps per body")
    num_envs: int = Field(32, ge=1)
    training_seed: int = Field(1409, description="the same for every lifetime (the paper's)")
    seed: int = Field(0, description="seeds the initial bodies and the tournaments")
    lease_s: float = Field(60.0, gt=0, description="a job without progress this long is reassigned")
    eval_top: int = Field(0, ge=0, description="best bodies evaluated on the test tasks at the end")
    eval_tasks: tuple[str, ...] = ()
    eval_seeds: int = Field(1, ge=1)
    eval_steps: int = Field(1_000_000, ge=1)

    @model_validator(mode="after")
    def _consistent(self) -> EvolutionConfig:
        unknown = set(self.eval_tasks) - set(TASKS)
        if unknown:
            raise ValueError(f"unknown eval tasks {sorted(unknown)}; choose from {sorted(TASKS)}")
        if self.total < self.population:
            raise ValueError(f"total ({self.total}) < population ({self.population})")
        if self.eval_top and not self.eval_tasks:
            raise ValueError("eval_top needs eval_tasks")
        return self


TEST_TASKS = (
    "patrol",
    "point_nav",
    "obstacle",
    "exploration",
    "escape",
    "incline",
    "push_box_incline",
    "manipulate_ball",
)
"""The paper's eight test tasks (appendix C)."""

PROFILES: dict[str, EvolutionConfig] = {
    "smoke": EvolutionConfig(
        name="smoke",
        population=4,
        tournament=2,
        total=8,
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
        total=96,
        train_steps=300_000,
        eval_top=2,
        eval_tasks=TEST_TASKS,
        eval_steps=100_000,
    ),
    "paper": EvolutionConfig(name="paper", eval_top=10, eval_tasks=TEST_TASKS, eval_seeds=5),
}


def load_profile(name_or_path: str, **overrides: object) -> EvolutionConfig:
    """A built-in profile by name, or a YAML file; `overrides` (e.g. world) win."""
    if name_or_path in PROFILES:
        base: dict[str, object] = PROFILES[name_or_path].model_dump()
    else:
        path = Path(name_or_path)
        if not path.is_file():
            raise ValueError(
                f"no profile {name_or_path!r}: use {', '.join(PROFILES)} or a YAML file"
            )
        data = yaml.safe_load(path.read_text()) or {}
        if not isinstance(data, dict):
            raise ValueError(f"{path}: a profile is a mapping of settings")
        parent = data.pop("profile", None)
        base = {**(PROFILES[parent].model_dump() if parent else {}), "name": path.stem, **data}
    chosen = {k: v for k, v in overrides.items() if v is not None}
    return EvolutionConfig.model_validate({**base, **chosen})
