"""PPO lifetime learning on a batched environment: rollouts, GAE, clipped updates, fitness.

One iteration collects `rollout_steps` batched steps into preallocated numpy buffers (the network
reads them through shared-memory torch views), computes GAE, and runs `epochs` passes of shuffled
minibatches, until a minibatch's approximate KL exceeds `kl_stop` (the released code's early
stop). The step that ends an episode at its time limit gets advantage 0 and its own value
as the return, and the steps before it bootstrap from that step's value (the released code's
`Buffer.compute_returns`); a termination bootstraps from nothing. The fitness and the learning
curve come from raw (unscaled) reward components.

Every iteration reports what PPO libraries log (`Diagnostics`: the losses, entropy, approximate
KL, clip fraction, explained variance, learning rate), from values the update computes anyway.
A training can be stopped at the end of an iteration and resumed bit for bit (`Saver`,
`train(..., resume=...)`): its state holds the network and Adam's moments, the normalisers, the
random generators, the episode bookkeeping, the next observation and the environment's whole
state (`derl.rl.snapshot`), taken at the end of an iteration where the environment can be
restored exactly.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from derl.rl import snapshot
from derl.rl.checkpoint import Checkpoint, state_from_bytes, state_to_bytes
from derl.rl.config import PPOConfig
from derl.rl.env_api import BatchedEnv
from derl.rl.episodes import EpisodeLog, EpisodeTracker, FitnessSource
from derl.rl.fused import FusedActorCritic, Minibatch
from derl.rl.loss import PPOCoefficients
from derl.rl.network import ActorCritic
from derl.rl.normalize import ObsNormalizer, RewardScaler

Initial = Callable[[ActorCritic, ObsNormalizer], None]
"""What a training starts from instead of the fresh network and normaliser: a change of them."""


@dataclass(frozen=True)
class Diagnostics:
    """One iteration's update, as PPO libraries log it: means over its minibatch steps (NaN
    where the approximate KL stopped it before its first)."""

    policy_loss: float
    """The clipped surrogate loss, -mean(min(ratio A, clip(ratio) A))."""
    value_loss: float
    """0.5 mean(max((V - R)^2, (V_clipped - R)^2)), before `value_coef`."""
    entropy: float
    """The policy's entropy per action dimension after the update (nats; the bonus's term)."""
    approx_kl: float
    """mean(old log-prob - log-prob), the estimate the early stop compares with `kl_stop`."""
    clip_fraction: float
    """Share of ratios outside [1 - clip, 1 + clip]."""
    explained_variance: float
    """1 - Var(R - V) / Var(R) of the rollout's value targets R and values V before the update."""
    learning_rate: float
    minibatches: int
    """Minibatch steps taken."""


@dataclass(frozen=True)
class Progress:
    """Handed to the callback once per iteration (and kept: `TrainResult.progress`)."""

    iteration: int
    """Iterations done (1-based)."""
    iterations: int
    env_steps: int
    recent_return: float | None
    """Mean fitness-component sum of the last finished episodes (None before two finished)."""
    steps_per_second: float
    """Env steps per second of this process's part of the training so far."""
    diagnostics: Diagnostics | None = None
    episodes: int = 0
    """Episodes finished in this iteration."""
    episode_return: float | None = None
    """Mean raw-reward sum of the last `recent_episodes` finished episodes (None before one
    finished; Stable-Baselines3's ep_rew_mean)."""
    episode_length: float | None = None
    """Their mean length in control steps (ep_len_mean)."""


@dataclass
class Saver:
    """When a training saves the state it can resume from: every `every` iterations (0: never)
    and when `stop` is set, at the end of the first iteration from then on where the
    environment can be restored exactly (`derl.rl.snapshot.capturable`: not while a body about
    to fall asleep touches another). `save` gets the result so far and the state's bytes;
    after a save that `stop` asked for, `train` returns that result. With `last`, the state at
    the end is saved too (what an extension of the training goes on from), where it can be."""

    save: Callable[[TrainResult, bytes], None]
    every: int = 0
    stop: threading.Event = field(default_factory=threading.Event)
    last: bool = False


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
    progress: list[Progress] = field(default_factory=list)
    """Every iteration's `Progress`, diagnostics included."""
    iterations: int = 0
    """Iterations done: `config.iterations`, or fewer where a `Saver` stopped the training."""


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

    def __init__(self, env: BatchedEnv, config: PPOConfig, initial: Initial | None = None) -> None:
        """`initial` changes the fresh network and observation normaliser before training
        starts (`derl.rl.inherit`)."""
        if env.num_envs != config.num_envs:
            raise ValueError(f"env has {env.num_envs} copies, config.num_envs={config.num_envs}")
        torch.set_num_threads(config.torch_threads)
        torch.manual_seed(config.seed)
        self.env = env
        self.config = config
        self.net = ActorCritic(env.obs_spaces, env.action_dim)
        self.obs_norm = ObsNormalizer(env.obs_spaces, config.obs_clip)
        if initial is not None:
            initial(self.net, self.obs_norm)
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
        self.reward_scaler = RewardScaler(env.num_envs, config.gamma, config.reward_clip)
        self.episodes = EpisodeTracker(
            env.num_envs, config.fitness_component, config.recent_episodes
        )
        self.buf = _Rollout(config.rollout_steps, env.num_envs, env.obs_spaces, env.action_dim)
        self.env_steps = 0
        self.iteration = 0  # done
        self.env_s = self.inference_s = self.update_s = 0.0
        self.earlier_s = self.earlier_physics_s = 0.0  # of the processes before a resume
        self.sparse_rows = self.sparse_nonzero = 0
        self.kl_stops = 0
        self.progress: list[Progress] = []
        self.diagnostics: Diagnostics | None = None

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
        lr = config.lr * (1.0 - iteration / config.iterations)
        fused.set_lr(lr)
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
        fused.losses.reset()
        if not self._epochs(mb, sources, nonzero, aux):
            self.kl_stops += 1
        for rows in buf.obs.values():
            rows[0] = rows[-1]  # the last observation starts the next rollout
        self.diagnostics = self._diagnostics(returns, lr)
        self.update_s += time.perf_counter() - t0

    def _diagnostics(self, returns: np.ndarray, lr: float) -> Diagnostics:
        """The update's `Diagnostics`, from what it computed (the losses: `fused.losses`)."""
        policy_loss, value_loss, approx_kl, clip_fraction = self.fused.losses.means()
        variance = float(np.var(returns))
        unexplained = float(np.var(returns - self.buf.values[:-1]))
        log_std = self.fused.log_std.numpy()
        return Diagnostics(
            policy_loss=policy_loss,
            value_loss=value_loss,
            entropy=float(np.mean(log_std)) + 0.5 * math.log(2.0 * math.pi * math.e),
            approx_kl=approx_kl,
            clip_fraction=clip_fraction,
            explained_variance=1.0 - unexplained / variance if variance > 0 else math.nan,
            learning_rate=lr,
            minibatches=self.fused.losses.steps,
        )

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

    def result(self, wall_s: float, physics_s: float | None) -> TrainResult:
        """The result so far (`wall_s`, `physics_s`: this process's seconds of the training,
        its physics' part, where the environment counts it)."""
        wall = self.earlier_s + wall_s
        physics = None if physics_s is None else self.earlier_physics_s + physics_s
        fitness = self.episodes.fitness(self.env_steps, self.config.fitness_window_steps)
        spent = self.env_s + self.inference_s + self.update_s
        return TrainResult(
            fitness=fitness.value,
            fitness_source=fitness.source,
            fitness_episodes=fitness.episodes,
            curve=list(self.episodes.curve),
            episodes=self.episodes.log(),
            env_steps=self.env_steps,
            wall_time_s=wall,
            steps_per_second=self.env_steps / wall,
            time_split=TimeSplit(
                env_s=self.env_s,
                inference_s=self.inference_s,
                update_s=self.update_s,
                other_s=wall - spent,
                physics_s=physics,
            ),
            checkpoint=self.checkpoint(),
            flat_rows=1.0 - self.sparse_nonzero / self.sparse_rows if self.sparse_rows else None,
            kl_stops=self.kl_stops,
            progress=list(self.progress),
            iterations=self.iteration,
        )

    def state(self, wall_s: float, physics_s: float) -> dict[str, Any]:
        """Everything `load` needs to go on from here (`wall_s`, `physics_s`: the training's
        seconds so far, its physics' part)."""
        adam = self.fused.adam
        return {
            "config": self.config.model_dump_json(),
            "iteration": self.iteration,
            "env_steps": self.env_steps,
            "theta": self.fused.theta.clone(),
            "adam": [adam.exp_avgs[0].clone(), adam.exp_avg_sqs[0].clone(), adam.steps[0].clone()],
            "rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "obs_norm": _tensors(self.obs_norm.state_dict()),
            "reward_scaler": _tensors(self.reward_scaler.state_dict()),
            "episodes": _tensors(self.episodes.state_dict()),
            "obs": _tensors({key: rows[0] for key, rows in self.buf.obs.items()}),
            "seconds": [self.env_s, self.inference_s, self.update_s, wall_s, physics_s],
            "sparse": [self.sparse_rows, self.sparse_nonzero],
            "kl_stops": self.kl_stops,
            "progress": _tensors([dataclasses.asdict(point) for point in self.progress]),
            "env": snapshot.capture(self.env),
        }

    def load(self, state: dict[str, Any]) -> None:
        """Go on from `state` (`state`'s), instead of `reset`; `ValueError` where it is of
        another configuration. Only the budget may differ (`total_steps`, and the fitness window
        that scales with it), not below the iterations done: the training is extended, its
        learning rate decaying linearly from where the new budget puts it to 0 at its end."""
        budget = {"total_steps", "fitness_window_steps"}
        saved = PPOConfig.model_validate_json(state["config"])
        if saved.model_dump(exclude=budget) != self.config.model_dump(exclude=budget):
            raise ValueError("the training state is of another configuration")
        if state["iteration"] > self.config.iterations:
            raise ValueError(
                f"the training state is past this budget: {state['env_steps']:,} env steps done"
            )
        self.iteration, self.env_steps = state["iteration"], state["env_steps"]
        self.fused.theta.copy_(state["theta"])
        adam = self.fused.adam
        for mine, saved in zip(
            (adam.exp_avgs[0], adam.exp_avg_sqs[0], adam.steps[0]), state["adam"], strict=True
        ):
            mine.copy_(saved)
        self.rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        self.obs_norm.load_state_dict(_arrays(state["obs_norm"]))
        self.reward_scaler.load_state_dict(_arrays(state["reward_scaler"]))
        self.episodes.load_state_dict(_arrays(state["episodes"]))
        for key, rows in _arrays(state["obs"]).items():
            self.buf.obs[key][0] = rows
        self.env_s, self.inference_s, self.update_s, self.earlier_s, self.earlier_physics_s = state[
            "seconds"
        ]
        self.sparse_rows, self.sparse_nonzero = state["sparse"]
        self.kl_stops = state["kl_stops"]
        self.progress = [_progress(point) for point in state["progress"]]
        self.env.reset(self.config.seed)
        snapshot.restore(self.env, state["env"])


def _tensors(tree: Any) -> Any:
    """`tree` with numpy arrays as tensors and numpy scalars as Python's (`torch.load`'s
    ``weights_only`` reads them)."""
    if isinstance(tree, dict):
        return {key: _tensors(value) for key, value in tree.items()}
    if isinstance(tree, list | tuple):
        return [_tensors(value) for value in tree]
    if isinstance(tree, np.ndarray):
        return torch.from_numpy(np.array(tree))
    if isinstance(tree, np.generic):
        return tree.item()
    return tree


def _arrays(tree: Any) -> Any:
    """`_tensors` undone: tensors as numpy arrays."""
    if isinstance(tree, dict):
        return {key: _arrays(value) for key, value in tree.items()}
    if isinstance(tree, list):
        return [_arrays(value) for value in tree]
    if isinstance(tree, torch.Tensor):
        return tree.numpy()
    return tree


def _progress(point: dict[str, Any]) -> Progress:
    diagnostics = point["diagnostics"]
    return Progress(**{**point, "diagnostics": diagnostics and Diagnostics(**diagnostics)})


def train(
    env: BatchedEnv,
    config: PPOConfig,
    callback: Callable[[Progress], None] | None = None,
    *,
    saver: Saver | None = None,
    resume: bytes | None = None,
    initial: Initial | None = None,
) -> TrainResult:
    """Train a fresh actor-critic on `env` with PPO; same env, config and seed give the same run.
    `initial` changes the fresh network and observation normaliser first (an inherited
    controller: `derl.rl.inherit.Inheritance`; Adam and the reward scaler start fresh).
    With `saver`, its state is saved as it says (and it may stop the training); with `resume`
    (a state `saver` was given), the training goes on from there, `env` being built as the one
    that saved it was (any seed): it ends with the bits an unstopped one ends with."""
    start = time.perf_counter()
    physics_before = getattr(env, "physics_s", 0.0)
    trainer = _Trainer(env, config, initial)
    if resume is None:
        trainer.reset()
    else:
        trainer.load(state_from_bytes(resume))
        physics_before = getattr(env, "physics_s", 0.0)  # restored: the earlier's are kept
    steps_before, last_saved = trainer.env_steps, trainer.iteration

    def result() -> TrainResult:
        wall = time.perf_counter() - start
        physics = getattr(env, "physics_s", None)
        physics_s = None if physics is None else physics - physics_before
        return trainer.result(wall, physics_s)

    # numpy's BLAS (the sampling's products) on as many threads as torch's
    with threadpool_limits(config.torch_threads, user_api="blas"):
        while trainer.iteration < config.iterations:
            finished = trainer.episodes.count
            trainer.collect()
            trainer.update(trainer.iteration)
            trainer.iteration += 1
            recent = trainer.episodes.end_iteration(trainer.env_steps)
            episode_return, episode_length = trainer.episodes.recent_episodes()
            elapsed = time.perf_counter() - start
            progress = Progress(
                iteration=trainer.iteration,
                iterations=config.iterations,
                env_steps=trainer.env_steps,
                recent_return=recent,
                steps_per_second=(trainer.env_steps - steps_before) / elapsed,
                diagnostics=trainer.diagnostics,
                episodes=trainer.episodes.count - finished,
                episode_return=episode_return,
                episode_length=episode_length,
            )
            trainer.progress.append(progress)
            if callback is not None:
                callback(progress)
            if saver is None or trainer.iteration == config.iterations:
                continue
            due = saver.stop.is_set() or (
                saver.every > 0 and trainer.iteration - last_saved >= saver.every
            )
            if due and snapshot.capturable(env):
                done = result()
                physics_s = done.time_split.physics_s or 0.0
                saver.save(done, state_to_bytes(trainer.state(done.wall_time_s, physics_s)))
                last_saved = trainer.iteration
                if saver.stop.is_set():
                    return done
    done = result()
    if saver is not None and saver.last and snapshot.capturable(env):
        physics_s = done.time_split.physics_s or 0.0
        saver.save(done, state_to_bytes(trainer.state(done.wall_time_s, physics_s)))
    return done
