"""PPO configuration: the paper's hyperparameter table as defaults, validated by pydantic."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator


class PPOConfig(BaseModel):
    """Hyperparameters of one lifetime-learning run (the paper's table "PPO hyperparameters").

    Where the paper is silent the values follow the released code (agrimgupta92/derl).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    num_envs: int = Field(32, ge=1, description="environment copies stepped together")
    rollout_steps: int = Field(128, ge=1, description="steps per copy between two updates")
    total_steps: int = Field(5_000_000, ge=1, description="env-step budget (all copies)")
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
    obs_clip: float = Field(10.0, gt=0.0, description="normalised proprioception clipped to ±this")
    reward_clip: float = Field(10.0, gt=0.0, description="scaled rewards clipped to ±this")
    seed: int = Field(
        1409, ge=0, lt=2**64, description="seeds network init, action noise and minibatch order"
    )
    torch_threads: int = Field(1, ge=1, description="1: a second thread steals the sim's core")
    fitness_component: str = Field("forward", description="reward component the fitness sums")
    fitness_window_steps: int = Field(
        100_000, ge=1, description="fitness averages episodes finished in the last this many steps"
    )
    recent_episodes: int = Field(
        10, ge=1, description="episodes averaged by the learning curve (the original's deque)"
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
