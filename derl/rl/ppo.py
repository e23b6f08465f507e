"""PPO lifetime learning on a batched environment: rollouts, GAE, clipped updates, fitness.

One iteration collects `rollout_steps` batched steps into preallocated numpy buffers (the network
reads them through shared-memory torch views), computes GAE, and runs `epochs` passes of shuffled
minibatches, until a minibatch's approximate KL exceeds `kl_stop` (the released code's early
stop). The step that ends an episode at its time limit gets advantage 0 and its own value
as the return, and the steps before it bootstrap from that step's value (the released code's
`Buffer.compute_returns`); a termination bootstraps from nothing. The fitness and the learning
curve come from raw (unscaled) reward components.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from derl.rl.checkpoint import Checkpoint
from derl.rl.config import PPOConfig
from derl.rl.env_api import BatchedEnv
from derl.rl.episodes import EpisodeLog, EpisodeTracker, FitnessSource
from derl.rl.fused import FusedActorCritic, Minibatch, PPOCoefficients
from derl.rl.network import ActorCritic
from derl.rl.normalize import ObsNormalizer, RewardScaler


@dataclass(frozen=True)
class Progress:
    """Handed to the callback once per iteration."""

    iteration: int
    """Iterations done (1-based)."""
    iterations: int
    env_steps: int
    recent_return: float | None
    """Mean fitness-component sum of the last finished episodes (None before two finished)."""
    steps_per_second: float


@dataclass(frozen=True)
class TimeSplit:
    """Where the wall time went, in seconds."""

    env_s: float
    """`env.step` (simulation, observations, rewards, resets)."""
    inference_s: float
    """Network forward passes: the actions while sampling and the rollout's values."""
    update_s: float
    """GAE and the gradient updates."""
    other_s: float
    """Normalisation, buffer writes, episode bookkeeping, callbacks."""
    physics_s: float | None = None
    """The part of `env_s` inside the physics engine, where the environment counts it (its
    `physics_s` attribute, seconds; `derl.envs.UnimalEnv` does); None where it does not."""


@dataclass(frozen=True)
class TrainResult:
    """Outcome of one training run."""

    fitness: float
    """Mean episode sum of `config.fitness_component` (see `fitness_source`)."""
    fitness_source: FitnessSource
    """"window": the mean of the curve's values of the iterations in the last
    `fitness_window_steps` (the definition); "last_episodes": a single episode finished, its
    sum; "unfinished": no episode finished at all, the running partial sums were used."""
    fitness_episodes: int
    curve: list[tuple[int, float]]
    """Per iteration (once two episodes have finished, as the released code): (env steps, mean
    fitness-component sum over the last `recent_episodes` finished episodes)."""
    episodes: EpisodeLog
    env_steps: int
    wall_time_s: float
    steps_per_second: float
    time_split: TimeSplit
    checkpoint: Checkpoint
    flat_rows: float | None
    """Share of the heightmap rows that were all zero (flat ground), whose first-layer products
    the update and the values skipped; None without a heightmap."""
    kl_stops: int
    """Updates that the approximate KL stopped before their last minibatch (`kl_stop`)."""

    @property
    def num_episodes(self) -> int:
        return len(self.episodes)


def compute_gae(
    rewards: np.ndarray,
    values: np.ndarray,
    terminated: np.ndarray,
    truncated: np.ndarray,
    gamma: float,
    lam: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimates and value targets, each (T, N), as the released code
    computes them (`Buffer.compute_returns`).

    `values` is (T + 1, N): V(s_0) .. V(s_T), where s_{t+1} is the observation after the reset
    for copies that finished at step t. A terminated step has no next value. A truncated step
    (the time limit, terminated or not) has advantage 0 and return V(s_t): its reward is not
    used, and the steps before it bootstrap from V(s_t). Both end the lambda-trace.
    """
    done = terminated | truncated
    deltas = rewards + gamma * values[1:] * ~done - values[:-1]
    deltas[truncated] = 0.0
    carry = gamma * lam * ~done
    advantages = np.zeros_like(deltas)
    last = np.zeros_like(deltas[0])
    for t in range(len(deltas) - 1, -1, -1):
        last = deltas[t] + carry[t] * last
        advantages[t] = last
    return advantages, advantages + values[:-1]


class _Rollout:
    """Preallocated buffers for one rollout; the first axis is time."""

    def __init__(
        self, steps: int, num_envs: int, obs_spaces: dict[str, int], action_dim: int
    ) -> None:
        f32 = np.float32
        # One extra row: the observation after the last step, carried to the next rollout.
        self.obs = {k: np.zeros((steps + 1, num_envs, d), f32) for k, d in obs_spaces.items()}
        self.obs_t = {k: torch.from_numpy(v) for k, v in self.obs.items()}
        self.noise = np.zeros((steps, num_envs, action_dim), f32)
        # The update's per-transition columns: actions (written while sampling), old log-prob,
        # advantage, old value, return. Gathered together per minibatch.
        self.aux = np.zeros((steps, num_envs, action_dim + 4), f32)
        self.actions = self.aux[..., :action_dim]
        self.values = np.zeros((steps + 1, num_envs), f32)
        self.rewards = np.zeros((steps, num_envs), f32)
        self.terminated = np.zeros((steps, num_envs), bool)
        self.truncated = np.zeros((steps, num_envs), bool)

    def obs_rows(self, t: int) -> dict[str, np.ndarray]:
        return {k: v[t] for k, v in self.obs.items()}


class _Trainer:
    """State of one training run; `train` drives it."""

    def __init__(self, env: BatchedEnv, config: PPOConfig) -> None:
        if env.num_envs != config.num_envs:
            raise ValueError(f"env has {env.num_envs} copies, config.num_envs={config.num_envs}")
        torch.set_num_threads(config.torch_threads)
        torch.manual_seed(config.seed)
        self.env = env
        self.config = config
        self.net = ActorCritic(env.obs_spaces, env.action_dim)
        self.fused = FusedActorCritic(self.net, config.lr, config.adam_eps)
        self.coef = PPOCoefficients(
            clip=config.clip,
            value_clip=config.value_clip,
            value_coef=config.value_coef,
            entropy_coef=config.entropy_coef,
            max_grad_norm=config.max_grad_norm,
            kl_stop=config.kl_stop,
        )
        self.rng = np.random.default_rng(config.seed)  # action noise and minibatch order
        self.obs_norm = ObsNormalizer(env.obs_spaces, config.obs_clip)
        self.reward_scaler = RewardScaler(env.num_envs, config.gamma, config.reward_clip)
        self.episodes = EpisodeTracker(
            env.num_envs, config.fitness_component, config.recent_episodes
        )
        self.buf = _Rollout(config.rollout_steps, env.num_envs, env.obs_spaces, env.action_dim)
        self.env_steps = 0
        self.env_s = self.inference_s = self.update_s = 0.0
        self.sparse_rows = self.sparse_nonzero = 0
        self.kl_stops = 0

    def reset(self) -> None:
        raw = self.env.reset(self.config.seed)
        self.obs_norm.update(raw)
        self.obs_norm.normalize(raw, out=self.buf.obs_rows(0))

    def collect(self) -> None:
        """Fill the rollout buffers; row 0 of the observations is already in place. Values are
        computed afterwards, in one pass (`_values`)."""
        buf, fused, clock = self.buf, self.fused, time.perf_counter
        fused.begin_sampling()
        # the whole rollout's action noise in one call: the same draws as one call per step
        self.rng.standard_normal(dtype=np.float32, out=buf.noise)
        for t in range(self.config.rollout_steps):
            t0 = clock()
            fused.act(buf.obs_rows(t), buf.noise[t], buf.actions[t])
            t1 = clock()
            step = self.env.step(buf.actions[t])  # unclipped: the env clips what it applies
            t2 = clock()
            self.env_s += t2 - t1
            self.inference_s += t1 - t0
            done = step.terminated | step.truncated
            self.env_steps += self.env.num_envs
            self.episodes.step(step.reward, step.components, done, self.env_steps)
            buf.rewards[t] = self.reward_scaler.scale(step.reward, done)
            buf.terminated[t] = step.terminated
            buf.truncated[t] = step.truncated
            self.obs_norm.update(step.obs)
            self.obs_norm.normalize(step.obs, out=buf.obs_rows(t + 1))

    def _values(self, obs: dict[str, torch.Tensor], nonzero: list[torch.Tensor | None]) -> None:
        """V of every observation of the rollout (`obs`, one row per step and copy, with their
        `nonzero` rows)."""
        t0 = time.perf_counter()
        self.buf.values.reshape(-1)[:] = self.fused.values(obs, nonzero=nonzero)
        self.inference_s += time.perf_counter() - t0

    def update(self, iteration: int) -> None:
        """Values, GAE, then the minibatch passes over the rollout (`_epochs`)."""
        config, buf, fused = self.config, self.buf, self.fused
        count = buf.values.size  # rows: every step of every copy, and the next observation
        obs = {k: v.view(count, -1) for k, v in buf.obs_t.items()}
        nonzero = fused.nonzero_rows(obs)
        for flags in nonzero:
            if flags is not None:
                self.sparse_rows += len(flags)
                self.sparse_nonzero += int(flags.sum())
        self._values(obs, nonzero)
        t0 = time.perf_counter()
        fused.set_lr(config.lr * (1.0 - iteration / config.iterations))
        advantages, returns = compute_gae(
            buf.rewards,
            buf.values,
            buf.terminated,
            buf.truncated,
            config.gamma,
            config.gae_lambda,
        )
        a_dim = self.env.action_dim
        buf.aux[..., a_dim] = fused.log_prob_of_noise(buf.noise)
        buf.aux[..., a_dim + 1] = (advantages - advantages.mean()) / (advantages.std() + 1e-5)
        buf.aux[..., a_dim + 2] = buf.values[:-1]
        buf.aux[..., a_dim + 3] = returns
        n, size = config.batch_size, config.minibatch_size
        sources = [obs[k][:n] for k in fused.keys]
        aux = torch.from_numpy(buf.aux.reshape(n, -1))
        mb = fused.minibatch(size, [s.shape[1] for s in sources], aux.shape[1])
        if not self._epochs(mb, sources, nonzero, aux):
            self.kl_stops += 1
        for rows in buf.obs.values():
            rows[0] = rows[-1]  # the last observation starts the next rollout
        self.update_s += time.perf_counter() - t0

    def _epochs(
        self,
        mb: Minibatch,
        sources: list[torch.Tensor],
        nonzero: list[torch.Tensor | None],
        aux: torch.Tensor,
    ) -> bool:
        """`epochs` passes of shuffled minibatches; False where a minibatch's approximate KL
        stopped them (the released code returns from its update there)."""
        n, size = self.config.batch_size, self.config.minibatch_size
        for _ in range(self.config.epochs):
            order = torch.from_numpy(self.rng.permutation(n))
            for start in range(0, n - size + 1, size):
                mb.gather(sources, nonzero, aux, order[start : start + size])
                if not self.fused.step(mb, self.coef):
                    return False
        return True

    def checkpoint(self) -> Checkpoint:
        self.fused.store_into_net()
        return Checkpoint.capture(self.net, self.obs_norm, self.config)


def train(
    env: BatchedEnv,
    config: PPOConfig,
    callback: Callable[[Progress], None] | None = None,
) -> TrainResult:
    """Train a fresh actor-critic on `env` with PPO; same env, config and seed give the same run."""
    start = time.perf_counter()
    physics_before = getattr(env, "physics_s", 0.0)
    trainer = _Trainer(env, config)
    trainer.reset()
    # numpy's BLAS (the sampling's products) on as many threads as torch's
    with threadpool_limits(config.torch_threads, user_api="blas"):
        for iteration in range(config.iterations):
            trainer.collect()
            trainer.update(iteration)
            recent = trainer.episodes.end_iteration(trainer.env_steps)
            if callback is not None:
                elapsed = time.perf_counter() - start
                callback(
                    Progress(
                        iteration=iteration + 1,
                        iterations=config.iterations,
                        env_steps=trainer.env_steps,
                        recent_return=recent,
                        steps_per_second=trainer.env_steps / elapsed,
                    )
                )
    wall = time.perf_counter() - start
    physics_s = getattr(env, "physics_s", None)
    fitness = trainer.episodes.fitness(trainer.env_steps, config.fitness_window_steps)
    return TrainResult(
        fitness=fitness.value,
        fitness_source=fitness.source,
        fitness_episodes=fitness.episodes,
        curve=trainer.episodes.curve,
        episodes=trainer.episodes.log(),
        env_steps=trainer.env_steps,
        wall_time_s=wall,
        steps_per_second=trainer.env_steps / wall,
        time_split=TimeSplit(
            env_s=trainer.env_s,
            inference_s=trainer.inference_s,
            update_s=trainer.update_s,
            other_s=wall - trainer.env_s - trainer.inference_s - trainer.update_s,
            physics_s=None if physics_s is None else physics_s - physics_before,
        ),
        checkpoint=trainer.checkpoint(),
        flat_rows=(
            1.0 - trainer.sparse_nonzero / trainer.sparse_rows if trainer.sparse_rows else None
        ),
        kl_stops=trainer.kl_stops,
    )
