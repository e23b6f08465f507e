"""PPO configuration: the paper's hyperparameter table as defaults, validated by pydantic."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, model_validator

SAVED = {"saved": True}
"""The validation context of settings read back from a file derl wrote (`profile.json`,
`study.json`): see `PPOHyperparameters._job_settings_of_old_files`."""


class PPOHyperparameters(BaseModel):
    """The paper's table "PPO hyperparameters": what a run or a study sets under `ppo`.

    Where the paper is silent the values follow the released code (agrimgupta92/derl). Each
    job's copies, budget, seed and fitness settings are not among them: they come from the
    profile's own fields and the job's task (`PPOConfig`).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    rollout_steps: int = Field(128, ge=1, description="steps per copy between two updates")
    gamma: float = Field(0.99, gt=0.0, le=1.0, description="discount factor")
    gae_lambda: float = Field(0.95, ge=0.0, le=1.0, description="λ of the advantage estimate (GAE)")
    clip: float = Field(0.2, gt=0.0, description="PPO ratio clip")
    value_clip: float = Field(0.2, gt=0.0, description="clip of the value change (clipped loss)")
    value_coef: float = Field(0.5, ge=0.0, description="weight of the value loss")
    entropy_coef: float = Field(0.01, ge=0.0, description="weight of the entropy bonus")
    epochs: int = Field(4, ge=1, description="passes over each rollout per update")
    minibatch_size: int = Field(512, ge=1, description="incomplete last minibatch is dropped")
    lr: float = Field(3e-4, gt=0.0, description="Adam learning rate, decayed linearly to 0")
    adam_eps: float = Field(1e-5, gt=0.0, description="Adam's epsilon")
    max_grad_norm: float = Field(0.5, gt=0.0, description="gradients clipped to this global norm")
    kl_stop: float = Field(
        0.2,
        gt=0.0,
        description="an update stops at the first minibatch whose approximate KL to the "
        "rollout's policy exceeds this (the released code's KL_TARGET_COEF 20 x 0.01)",
    )
    obs_clip: float = Field(10.0, gt=0.0, description="normalised proprioception clipped to ±this")
    reward_clip: float = Field(10.0, gt=0.0, description="scaled rewards clipped to ±this")
    torch_threads: int = Field(1, ge=1, description="1: a second thread steals the sim's core")
    recent_episodes: int = Field(
        10, ge=1, description="episodes averaged by the learning curve (the original's deque)"
    )

    @model_validator(mode="before")
    @classmethod
    def _job_settings_of_old_files(cls, data: object, info: ValidationInfo) -> object:
        """derl wrote every `PPOConfig` field under a saved run's or study's `ppo` until
        2026-12-03, each job's copies, budget, seed and fitness settings included, which no job
        used (theirs came from the profile's fields): dropped from such a file (`SAVED`); in a
        profile they are unknown keys."""
        if info.context == SAVED and isinstance(data, dict):
            unused = PPOConfig.model_fields.keys() - cls.model_fields.keys()
            return {key: value for key, value in data.items() if key not in unused}
        return data


class PPOConfig(PPOHyperparameters):
    """One lifetime-learning run's whole configuration: the hyperparameters, and its copies,
    budget, seed and fitness settings (in a run: `num_envs`, `train_steps` or `eval_steps`,
    `training_seed` or an evaluation's seed, and the task's fitness)."""

    num_envs: int = Field(32, ge=1, description="environment copies stepped together")
    total_steps: int = Field(5_000_000, ge=1, description="env-step budget (all copies)")
    seed: int = Field(
        1409, ge=0, lt=2**64, description="seeds network init, action noise and minibatch order"
    )
    fitness_component: str = Field("forward", description="reward component the fitness sums")
    fitness_window_steps: int = Field(
        409_600,
        ge=1,
        description="the fitness averages the curve's values of the iterations in the last this "
        "many steps (a run's: the released code's last 100 of 1220 iterations, as a share of "
        "the budget)",
    )

    @property
    def batch_size(self) -> int:
        """Transitions collected per iteration."""
        return self.num_envs * self.rollout_steps

    @property
    def iterations(self) -> int:
        """Number of collect-and-update iterations (the budget rounded down to whole rollouts)."""
        return self.total_steps // self.batch_size

    @model_validator(mode="after")
    def _check_sizes(self) -> PPOConfig:
        if self.iterations < 1:
            raise ValueError(f"total_steps {self.total_steps} < one rollout ({self.batch_size})")
        if self.minibatch_size > self.batch_size:
            raise ValueError(
                f"minibatch_size {self.minibatch_size} > rollout batch {self.batch_size}"
            )
        return self
