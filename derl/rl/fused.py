"""The actor-critic's sampling, values and PPO minibatch step written out by hand, on one flat
float32 parameter vector and without autograd: the same arithmetic at a fraction of the per-op
cost of small layers, an optimisation of the loss as defined in `derl.rl.loss`.

`ActorCritic` (network.py) defines and initialises the network; `FusedActorCritic` copies its
weights into one flat vector (`store_into_net` copies them back) and runs

- `act`: the actor on one batched step, Gaussian noise from a numpy generator, in numpy (on
  numpy views of the same weights): between two physics steps, which evict the caches, numpy's
  few small calls cost a third of torch's (FT, 10 limbs: 59 us against 190 us a step);
- `values`: the critic on many rows at once (a rollout's values are computed after it);
- `step`: one minibatch of the clipped PPO loss of the released code (`derl.rl.loss.ppo_loss`:
  clipped surrogate, clipped value loss, entropy bonus as the mean over action dimensions), its
  gradient by the chain rule, gradient-norm clipping and one step of torch's fused Adam kernel
  on the flat vector, called directly, unless the minibatch's approximate KL exceeds its limit
  (the released code's early stop) (`torch.optim.Adam` costs ~0.14 ms a step around it, and its
  constructor imports torch._dynamo: ~0.8 s once per process).

Weights are stored input-major, (in, out): torch's `nn.Linear.weight` transposed. The update's
products are torch's (MKL; one thread under `torch.set_num_threads(1)`), the sampling's numpy's
(OpenBLAS; the trainer limits it to as many threads), tanh is numpy's, in place on the same
memory (torch 2.13's CPU tanh is ~10x slower than numpy's). Buffers are allocated once per batch
size. The loss's terms and gradient equal autograd's on `derl.rl.loss.ppo_loss` to float32
rounding (tests/test_ppo.py). Heightmap rows that are all zero skip their first-layer product
(`SPARSE`): the same arithmetic.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np
import torch
from torch import nn

from derl.rl.architecture import HIDDEN
from derl.rl.loss import PPOCoefficients
from derl.rl.network import ActorCritic, Encoder

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
SPARSE = "heightmap"
"""The observation type whose rows are mostly all zero (a head over flat ground reads zeros;
in VT trainings of the bench bodies 84-100% of rows): in the update and the values, the first
layer of its branch multiplies only the other rows. A zero row's product is 0: its output is the
bias, and it adds nothing to the weight's gradient, so this is the same arithmetic."""
_tanh_backward = torch.ops.aten.tanh_backward.grad_input
"""grad_input = grad_output * (1 - output^2), one kernel."""


_Buffer = TypeVar("_Buffer", torch.Tensor, np.ndarray)
_At = list[torch.Tensor | None]
"""Per branch: the positions of the rows its input holds, or None where it holds every row."""


class _Slab:
    """Hands out consecutive views of a flat parameter vector and of its gradient."""

    def __init__(self, size: int) -> None:
        self.theta = torch.zeros(size)
        self.grad = torch.zeros(size)
        self.used = 0

    def take(self, *shape: int) -> tuple[torch.Tensor, torch.Tensor]:
        end = self.used + math.prod(shape)
        views = self.theta[self.used : end].view(shape), self.grad[self.used : end].view(shape)
        self.used = end
        return views


class _Linear:
    """Views of one layer's weight (in, out), bias (out,) and their gradients."""

    def __init__(self, slab: _Slab, module: nn.Linear) -> None:
        self.module = module
        self.w, self.gw = slab.take(module.in_features, module.out_features)
        self.b, self.gb = slab.take(module.out_features)
        self.w_np, self.b_np = self.w.numpy(), self.b.numpy()

    def load(self) -> None:
        self.w.copy_(self.module.weight.detach().T)
        self.b.copy_(self.module.bias.detach())

    def store(self) -> None:
        with torch.no_grad():
            self.module.weight.copy_(self.w.T)
            self.module.bias.copy_(self.b)


@dataclass
class _Activations(Generic[_Buffer]):
    """Forward buffers of one tower for a batch of `rows`: torch tensors (the update, the
    values) or numpy arrays (sampling). `f` is the encoding the head reads: the fuse layer's
    output, or without one the single branch's (`a2[0]`, the same buffer)."""

    a1: list[_Buffer]
    a2: list[_Buffer]
    f: _Buffer
    y: _Buffer

    @classmethod
    def allocate(
        cls,
        rows: int,
        branches: int,
        out: int,
        empty: Callable[[int, int], _Buffer],
        fuse: bool,
    ) -> _Activations[_Buffer]:
        a2 = [empty(rows, HIDDEN) for _ in range(branches)]
        return cls(
            a1=[empty(rows, HIDDEN) for _ in range(branches)],
            a2=a2,
            f=empty(rows, HIDDEN) if fuse else a2[0],
            y=empty(rows, out),
        )


def _numpy_empty(rows: int, cols: int) -> np.ndarray:
    return np.empty((rows, cols), np.float32)


def _layer(sequence: nn.Module, index: int) -> nn.Linear:
    """The linear layer `index` of one of an `Encoder`'s `nn.Sequential`s."""
    assert isinstance(sequence, nn.Sequential)
    layer = sequence[index]
    assert isinstance(layer, nn.Linear)
    return layer


class _Tower:
    """One encoder and its linear head (the actor's mean or the critic's value)."""

    def __init__(self, slab: _Slab, encoder: Encoder, head: nn.Linear) -> None:
        self.branches = [
            (
                _Linear(slab, _layer(encoder.branches[key], 0)),
                _Linear(slab, _layer(encoder.branches[key], 2)),
            )
            for key in encoder.keys
        ]
        self.layers = [layer for pair in self.branches for layer in pair]
        self.fuse = None if encoder.fuse is None else _Linear(slab, _layer(encoder.fuse, 0))
        if self.fuse is not None:
            self.layers.append(self.fuse)
            rows = range(0, HIDDEN * len(self.branches), HIDDEN)
            self.fuse_w = [self.fuse.w[r : r + HIDDEN] for r in rows]
            self.fuse_gw = [self.fuse.gw[r : r + HIDDEN] for r in rows]
            self.fuse_w_np = [w.numpy() for w in self.fuse_w]
        self.head = _Linear(slab, head)
        self.layers.append(self.head)
        self.sparse = [key == SPARSE for key in encoder.keys]

    def activations(self, rows: int, empty: Callable[[int, int], _Buffer]) -> _Activations[_Buffer]:
        """Buffers for `rows`, of `empty`'s kind (`torch.empty`, or numpy's for sampling)."""
        out = self.head.module.out_features
        return _Activations.allocate(rows, len(self.branches), out, empty, self.fuse is not None)

    def forward(
        self, xs: list[torch.Tensor], at: _At, act: _Activations[torch.Tensor]
    ) -> torch.Tensor:
        """(rows, out) head output for one input per observation type: (rows, dim), or where
        `at` gives them, only the rows at those positions (the others are zero)."""
        for (first, second), x, rows, a1, a2 in zip(
            self.branches, xs, at, act.a1, act.a2, strict=True
        ):
            if rows is None:
                torch.addmm(first.b, x, first.w, out=a1)
            else:
                a1.copy_(first.b)
                if len(rows):
                    a1.index_copy_(0, rows, torch.addmm(first.b, x, first.w))
            _tanh(a1)
            _tanh(torch.addmm(second.b, a1, second.w, out=a2))
        if self.fuse is not None:
            torch.addmm(self.fuse.b, act.a2[0], self.fuse_w[0], out=act.f)
            for a2, w in zip(act.a2[1:], self.fuse_w[1:], strict=True):
                act.f.addmm_(a2, w)
            _tanh(act.f)
        return torch.addmm(self.head.b, act.f, self.head.w, out=act.y)

    def forward_numpy(self, xs: list[np.ndarray], act: _Activations[np.ndarray]) -> np.ndarray:
        """`forward` in numpy, for one batched step while sampling (a `SPARSE` input that is all
        zero skips its first product)."""
        for (first, second), x, sparse, a1, a2 in zip(
            self.branches, xs, self.sparse, act.a1, act.a2, strict=True
        ):
            if sparse and not np.count_nonzero(x):
                np.copyto(a1, first.b_np)
                np.tanh(a1, out=a1)
            else:
                _affine_tanh(x, first, a1)
            _affine_tanh(a1, second, a2)
        if self.fuse is not None:
            np.matmul(act.a2[0], self.fuse_w_np[0], out=act.f)
            for a1, a2, w in zip(act.a1[1:], act.a2[1:], self.fuse_w_np[1:], strict=True):
                np.add(act.f, np.matmul(a2, w, out=a1), out=act.f)  # a1: free by now
            np.add(act.f, self.fuse.b_np, out=act.f)
            np.tanh(act.f, out=act.f)
        np.matmul(act.f, self.head.w_np, out=act.y)
        return np.add(act.y, self.head.b_np, out=act.y)

    def backward(
        self,
        xs: list[torch.Tensor],
        at: _At,
        act: _Activations[torch.Tensor],
        g_y: torch.Tensor,
        tmp: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    ) -> None:
        """Write the gradients of every parameter given the gradient `g_y` of the head output;
        `tmp` are three (rows, HIDDEN) scratch buffers."""
        g_fuse, g_act, g_pre = tmp
        torch.mm(act.f.T, g_y, out=self.head.gw)
        torch.sum(g_y, 0, out=self.head.gb)
        torch.mm(g_y, self.head.w.T, out=g_act)  # the gradient of the encoding
        if self.fuse is None:
            (first, second), x, rows = self.branches[0], xs[0], at[0]
            _branch_backward(first, second, x, rows, act.a1[0], act.a2[0], g_act, g_pre)
            return
        _tanh_backward(g_act, act.f, grad_input=g_fuse)
        torch.sum(g_fuse, 0, out=self.fuse.gb)
        for (first, second), x, rows, a1, a2, w, gw in zip(
            self.branches, xs, at, act.a1, act.a2, self.fuse_w, self.fuse_gw, strict=True
        ):
            torch.mm(a2.T, g_fuse, out=gw)
            torch.mm(g_fuse, w.T, out=g_act)
            _branch_backward(first, second, x, rows, a1, a2, g_act, g_pre)


def _branch_backward(
    first: _Linear,
    second: _Linear,
    x: torch.Tensor,
    rows: torch.Tensor | None,
    a1: torch.Tensor,
    a2: torch.Tensor,
    g_a2: torch.Tensor,
    g_pre: torch.Tensor,
) -> None:
    """The gradients of one branch's two layers given `g_a2`, the gradient of its output
    (overwritten); `g_pre` is scratch. `x` holds the input's rows at `rows` (None: all)."""
    _tanh_backward(g_a2, a2, grad_input=g_pre)
    torch.mm(a1.T, g_pre, out=second.gw)
    torch.sum(g_pre, 0, out=second.gb)
    torch.mm(g_pre, second.w.T, out=g_a2)
    _tanh_backward(g_a2, a1, grad_input=g_pre)
    if rows is None:
        torch.mm(x.T, g_pre, out=first.gw)
    elif len(rows):
        torch.mm(x.T, g_pre.index_select(0, rows), out=first.gw)
    else:
        first.gw.zero_()
    torch.sum(g_pre, 0, out=first.gb)


def _affine_tanh(x: np.ndarray, layer: _Linear, out: np.ndarray) -> None:
    """out = tanh(x @ w + b), in numpy."""
    np.matmul(x, layer.w_np, out=out)
    np.add(out, layer.b_np, out=out)
    np.tanh(out, out=out)


def _tanh(x: torch.Tensor) -> None:
    """In-place tanh(x) = 2 sigmoid(2x) - 1: torch's vectorised sigmoid, the scalings in numpy on
    the tensor's memory. On a 512 x 64 minibatch activation it takes 43 us where np.tanh takes
    114 and torch.tanh 112 (scalar kernels on this CPU: tanh cost more than the layer's matrix
    product); it differs from tanh by at most 2e-7."""
    view = x.numpy()
    np.add(view, view, out=view)
    x.sigmoid_()
    np.add(view, view, out=view)
    np.subtract(view, 1.0, out=view)


class Minibatch:
    """Buffers of one minibatch of `rows`: gathered inputs, activations and gradient scratch."""

    def __init__(self, net: FusedActorCritic, rows: int, dims: list[int], aux: int) -> None:
        self.full = [torch.empty(rows, d) for d in dims]
        self.x = list(self.full)
        self.at: _At = [None] * len(dims)
        self.aux = torch.empty(rows, aux)
        self.actor = net.actor.activations(rows, torch.empty)
        self.critic = net.critic.activations(rows, torch.empty)
        self.g_mean = torch.empty(rows, net.action_dim)
        self.g_value = torch.empty(rows, 1)
        self.tmp = (torch.empty(rows, HIDDEN), torch.empty(rows, HIDDEN), torch.empty(rows, HIDDEN))

    def gather(
        self, sources: list[torch.Tensor], nonzero: _At, aux: torch.Tensor, idx: torch.Tensor
    ) -> None:
        """Rows `idx` of every source (only the non-zero ones of a source with `nonzero` flags,
        from `nonzero_rows`) and of `aux`."""
        for i, (source, flags, full) in enumerate(zip(sources, nonzero, self.full, strict=True)):
            if flags is None:
                torch.index_select(source, 0, idx, out=full)
                continue
            at = flags[idx].nonzero().squeeze(1)
            self.x[i], self.at[i] = full[: len(at)], at
            torch.index_select(source, 0, idx[at], out=self.x[i])
        torch.index_select(aux, 0, idx, out=self.aux)


class Losses:
    """The sums, over the minibatch steps taken since `reset`, of what `FusedActorCritic.step`
    computed on the way to its gradient: the clipped surrogate loss, the clipped value loss
    (before `value_coef`), the approximate KL (the early stop's) and the share of ratios outside
    the clip."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.steps = 0
        self.sums = [0.0, 0.0, 0.0, 0.0]

    def add(self, policy: float, value: float, kl: float, clipped: float) -> None:
        self.steps += 1
        for i, term in enumerate((policy, value, kl, clipped)):
            self.sums[i] += term

    def means(self) -> tuple[float, float, float, float]:
        """(policy loss, value loss, approximate KL, clip fraction), NaN without a step."""
        n = self.steps or math.nan
        policy, value, kl, clipped = (total / n for total in self.sums)
        return policy, value, kl, clipped


class FusedActorCritic:
    """An `ActorCritic`'s parameters in one flat vector, trained by `step` with Adam."""

    def __init__(self, net: ActorCritic, lr: float, adam_eps: float) -> None:
        self.net = net
        self.keys = net.actor.keys
        self.action_dim = net.action_dim
        slab = _Slab(sum(p.numel() for p in net.parameters()))
        self.actor = _Tower(slab, net.actor, net.mean_head)
        self.critic = _Tower(slab, net.critic, net.value_head)
        self.log_std, self.g_log_std = slab.take(net.action_dim)
        self.theta, self.grad = slab.theta, slab.grad
        self.load_from_net()
        self.adam = _Adam(self.theta, self.grad, lr, adam_eps)
        self.losses = Losses()
        self._acting: _Activations[np.ndarray] | None = None
        self._valuing: _Activations[torch.Tensor] | None = None
        self._minibatch: Minibatch | None = None

    def load_from_net(self) -> None:
        for layer in self.actor.layers + self.critic.layers:
            layer.load()
        self.log_std.copy_(self.net.log_std.detach())

    def store_into_net(self) -> None:
        """Copy the current parameters into the `ActorCritic` (for checkpoints)."""
        for layer in self.actor.layers + self.critic.layers:
            layer.store()
        with torch.no_grad():
            self.net.log_std.copy_(self.log_std)

    def act(self, obs: dict[str, np.ndarray], noise: np.ndarray, actions: np.ndarray) -> None:
        """Actions mean + std * noise for one batched step (`begin_sampling` first): `noise` holds
        standard normal draws, `actions` receives the result."""
        xs = [obs[key] for key in self.keys]
        if self._acting is None or self._acting.y.shape[0] != len(xs[0]):
            self._acting = self.actor.activations(len(xs[0]), _numpy_empty)
        mean = self.actor.forward_numpy(xs, self._acting)
        np.multiply(noise, self.std, out=actions)
        actions += mean

    def begin_sampling(self) -> None:
        """Cache exp(log_std) for `act` (the parameters stay fixed while sampling)."""
        self.std = torch.exp(self.log_std).numpy()

    def log_prob_of_noise(self, noise: np.ndarray) -> np.ndarray:
        """Log-density of actions mean + std * noise: (..., A) noise in, (...) out."""
        const = float(self.log_std.sum()) + self.action_dim * _HALF_LOG_2PI
        return -0.5 * np.square(noise).sum(-1) - np.float32(const)

    def nonzero_rows(self, obs: dict[str, torch.Tensor]) -> _At:
        """Per observation type: for `SPARSE`, which rows of `obs` are not all zero (bool);
        None for the others."""
        return [
            torch.from_numpy(np.logical_or.reduce(obs[key].numpy(), axis=1))  # 8x torch.any's
            if sparse
            else None
            for key, sparse in zip(self.keys, self.actor.sparse, strict=True)
        ]

    def values(self, obs: dict[str, torch.Tensor], nonzero: _At | None = None) -> np.ndarray:
        """(rows,) critic values (the buffers are kept for the next call of the same size);
        `nonzero`: `nonzero_rows(obs)` where already known."""
        nonzero = self.nonzero_rows(obs) if nonzero is None else nonzero
        xs, at = [], []
        for key, flags in zip(self.keys, nonzero, strict=True):
            rows = None if flags is None else flags.nonzero().squeeze(1)
            xs.append(obs[key] if rows is None else obs[key].index_select(0, rows))
            at.append(rows)
        act = self._valuing
        if act is None or act.y.shape[0] != len(obs[self.keys[0]]):
            act = self._valuing = self.critic.activations(len(obs[self.keys[0]]), torch.empty)
        return self.critic.forward(xs, at, act)[:, 0].numpy().copy()

    def minibatch(self, rows: int, dims: list[int], aux: int) -> Minibatch:
        """Buffers for `step` (allocated on the first call)."""
        if self._minibatch is None:
            self._minibatch = Minibatch(self, rows, dims, aux)
        return self._minibatch

    def step(self, mb: Minibatch, coef: PPOCoefficients) -> bool:
        """One PPO gradient step on the minibatch gathered in `mb` (`Minibatch.gather`): its
        inputs, and in `mb.aux` the columns [actions (A), old log-prob, advantage, old value,
        return]. The loss's gradient with respect to the heads' outputs is computed in numpy (on
        512 values, a numpy call costs a fraction of a torch call). False, and no step, where the
        minibatch's approximate KL, mean(old log-prob - log-prob), exceeds `coef.kl_stop` (the
        released code's `train_on_batch`, which then ends the update)."""
        a_dim, rows = self.action_dim, mb.aux.shape[0]
        aux = mb.aux.numpy()
        actions = aux[:, :a_dim]
        old_log_prob, adv, old_value, ret = aux[:, a_dim : a_dim + 4].T
        mean = self.actor.forward(mb.x, mb.at, mb.actor).numpy()
        value = self.critic.forward(mb.x, mb.at, mb.critic).numpy()[:, 0]
        log_std = self.log_std.numpy()

        # Policy: log pi(a) = sum(-z^2 / 2 - log_std - log(2 pi) / 2), z = (a - mean) / std.
        inv_std = np.exp(-log_std)
        z = np.subtract(actions, mean)
        z *= inv_std
        sq = np.square(z)
        log_prob = np.add.reduce(sq, axis=1)
        log_prob *= -0.5
        log_prob -= np.float32(np.add.reduce(log_std) + a_dim * _HALF_LOG_2PI)
        log_ratio = np.subtract(log_prob, old_log_prob, out=log_prob)
        approx_kl = -float(np.add.reduce(log_ratio)) / rows
        if approx_kl > coef.kl_stop:
            return False
        ratio = np.exp(log_ratio, out=log_ratio)
        outside = int(np.count_nonzero(np.abs(ratio - 1.0) > coef.clip))
        surr = ratio * adv
        clipped = np.minimum(np.maximum(ratio, 1.0 - coef.clip), 1.0 + coef.clip, out=ratio)
        clipped *= adv
        policy_loss = -float(np.add.reduce(np.minimum(surr, clipped))) / rows
        # d(-mean(min(surr, clipped)))/d log_prob: the min passes the unclipped term's gradient
        # (ratio * adv) where it is the smaller or the two are equal (ratio inside the clip).
        g_log_prob = np.multiply(surr, surr <= clipped, out=surr)
        g_log_prob *= -1.0 / rows
        z *= inv_std
        np.multiply(z, g_log_prob[:, None], out=mb.g_mean.numpy())
        # d log pi / d log_std = z^2 - 1; the entropy bonus is mean(log_std) + const.
        g_log_std = np.matmul(g_log_prob, sq, out=self.g_log_std.numpy())
        g_log_std -= np.float32(np.add.reduce(g_log_prob) + coef.entropy_coef / a_dim)

        # Value: 0.5 * mean(max((v - R)^2, (v_old + clip(v - v_old) - R)^2)), times value_coef.
        # The max passes the gradient of the larger term: err, or where the clipped one is larger
        # (by rounding alone while v - v_old lies within the clip) and v - v_old within the clip
        # (inclusive, as torch.clamp's gradient), clipped_err; else nothing.
        err = value - ret
        clipped_err = np.subtract(value, old_value)
        inside = np.abs(clipped_err) <= coef.value_clip
        np.minimum(np.maximum(clipped_err, -coef.value_clip), coef.value_clip, out=clipped_err)
        clipped_err += old_value
        clipped_err -= ret
        square, clipped_square = np.square(err), np.square(clipped_err)
        keep = square >= clipped_square
        value_loss = 0.5 * float(np.add.reduce(np.maximum(square, clipped_square))) / rows
        g_value = mb.g_value.numpy()[:, 0]
        np.copyto(g_value, np.where(keep, err, np.multiply(clipped_err, inside)))
        g_value *= coef.value_coef / rows

        self.actor.backward(mb.x, mb.at, mb.actor, mb.g_mean, mb.tmp)
        self.critic.backward(mb.x, mb.at, mb.critic, mb.g_value, mb.tmp)
        grad = self.grad.numpy()
        norm = math.sqrt(float(np.dot(grad, grad)))
        scale = coef.max_grad_norm / (norm + 1e-6)  # clip_grad_norm_'s formula
        if scale < 1.0:
            self.grad.mul_(scale)
        self.adam.step()
        self.losses.add(policy_loss, value_loss, approx_kl, outside / rows)
        return True

    def set_lr(self, lr: float) -> None:
        self.adam.lr = lr


class _Adam:
    """Adam (torch's defaults: betas 0.9, 0.999, no weight decay) on one flat parameter vector,
    by torch's fused CPU kernel: what `torch.optim.Adam(fused=True).step` runs, less its wrapper."""

    def __init__(self, theta: torch.Tensor, grad: torch.Tensor, lr: float, eps: float) -> None:
        self.lr, self.eps = lr, eps
        self.params, self.grads = [theta], [grad]
        self.exp_avgs, self.exp_avg_sqs = [torch.zeros_like(theta)], [torch.zeros_like(theta)]
        self.steps = [torch.zeros(())]

    def step(self) -> None:
        self.steps[0] += 1
        torch._fused_adam_(
            self.params,
            self.grads,
            self.exp_avgs,
            self.exp_avg_sqs,
            [],
            self.steps,
            lr=self.lr,
            beta1=0.9,
            beta2=0.999,
            weight_decay=0.0,
            eps=self.eps,
            amsgrad=False,
            maximize=False,
        )
