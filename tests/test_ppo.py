"""derl.rl: GAE, network, normalisation, checkpoints, reproducibility, learning on MuJoCo."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pydantic
import pytest
import torch

from derl.rl import (
    ActorCritic,
    BatchedEnv,
    Checkpoint,
    GymBatchedEnv,
    ObsNormalizer,
    Policy,
    PPOConfig,
    Progress,
    RewardScaler,
    RunningMeanStd,
    TrainResult,
    compute_gae,
    torch_archive,
    train,
)
from derl.rl.architecture import parameter_shapes
from derl.rl.episodes import EpisodeTracker
from derl.rl.fused import FusedActorCritic
from derl.rl.loss import PPOCoefficients, Samples, ppo_loss

DERL_OBS = {"proprioception": 50, "heightmap": 1410}


def test_config_defaults_are_the_papers_and_unknown_keys_fail() -> None:
    config = PPOConfig()
    assert (config.num_envs, config.rollout_steps, config.total_steps) == (32, 128, 5_000_000)
    assert (config.gamma, config.gae_lambda, config.clip, config.value_clip) == (
        0.99,
        0.95,
        0.2,
        0.2,
    )
    assert (config.epochs, config.minibatch_size, config.lr, config.max_grad_norm) == (
        4,
        512,
        3e-4,
        0.5,
    )
    assert config.iterations == 1220
    with pytest.raises(pydantic.ValidationError):
        PPOConfig(learning_rate=1e-3)
    with pytest.raises(pydantic.ValidationError):
        PPOConfig(num_envs=2, rollout_steps=8, minibatch_size=512)


def test_gae_by_hand_with_termination_and_truncation() -> None:
    # The released code's Buffer.compute_returns: copy 0 terminates at step 1; copy 1 hits the
    # time limit at step 1; copy 2 hits it at step 2 while also terminating (a timeout there).
    rewards = np.ones((3, 3), np.float32)
    values = np.array([[1, 5, 1], [2, 6, 1], [3, 7, 1], [4, 8, 1]], np.float32)
    terminated = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 1]], bool)
    truncated = np.array([[0, 0, 0], [0, 1, 0], [0, 0, 1]], bool)
    adv, ret = compute_gae(rewards, values, terminated, truncated, 0.5, 0.5)
    # Copy 0: d2 = 1 + .5*4 - 3 = 0; d1 = 1 - 2 = -1 (no bootstrap); d0 = 1 + .5*2 - 1 = 1,
    #   A0 = d0 + .25*A1 = .75.
    # Copy 1: A1 = 0 (its reward unused, its return V(s1) = 6); d2 = 1 + .5*8 - 7 = -2;
    #   d0 = 1 + .5*6 - 5 = -1 bootstraps from V(s1), A0 = -1 + .25*0 = -1.
    # Copy 2: A2 = 0; d1 = 1 + .5*1 - 1 = .5 = A1; A0 = .5 + .25*.5 = .625.
    expected = np.array([[0.75, -1.0, 0.625], [-1.0, 0.0, 0.5], [0.0, -2.0, 0.0]])
    np.testing.assert_allclose(adv, expected, atol=1e-6)
    np.testing.assert_allclose(ret, expected + values[:-1], atol=1e-6)


def test_network_shapes_and_init() -> None:
    torch.manual_seed(0)
    net = ActorCritic(DERL_OBS, 12)
    actor = {id(p) for p in net.actor.parameters()}
    assert actor.isdisjoint(id(p) for p in net.critic.parameters())
    assert net.actor.fuse[0].in_features == 128
    assert torch.equal(net.log_std, torch.zeros(12))
    assert all(not m.bias.any() for m in net.modules() if isinstance(m, torch.nn.Linear))
    # One observation type: its MLP straight into the heads (the released MLPObsEncoder)
    single = ActorCritic({"proprioception": 4}, 1)
    assert single.actor.fuse is None and single.critic.fuse is None
    assert sum(p.numel() for p in single.actor.parameters()) == (4 + 1) * 64 + 65 * 64
    assert single.action_mean({"proprioception": torch.zeros(3, 4)}).shape == (3, 1)


@pytest.mark.parametrize(
    "spaces", [{"proprioception": 4}, DERL_OBS, {"proprioception": 30, "goal": 3, "box": 9}]
)
def test_the_torch_free_architecture_names_the_networks_parameters(spaces: dict[str, int]) -> None:
    """What a coordinator checks a checkpoint against (`parameter_shapes`, no torch) is the state
    dict of the network a trainer builds."""
    net = ActorCritic(spaces, 5)
    assert {k: tuple(v.shape) for k, v in net.state_dict().items()} == parameter_shapes(spaces, 5)


class _Code:
    """An object whose unpickling would run code."""

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (print, ("ran",))


def test_the_torch_free_reader_reads_what_torch_reads_and_runs_no_code() -> None:
    """`torch_archive.load` gives torch.load's (weights-only) tensors as arrays, views (a
    transposed weight, a slice, a 0-d count, several dtypes) included; it refuses any other
    global, what is not plain data, and a tensor that reaches past its storage."""
    base = torch.arange(24, dtype=torch.float32).reshape(4, 6)
    tree = {
        "t": base.T, "slice": base[1:3, 2:], "count": torch.tensor(3.0, dtype=torch.float64),
        "ints": torch.arange(5), "mask": torch.tensor([True, False]), "empty": torch.zeros(0, 3),
        "nested": [1, "a", (2.5, None), {"k": torch.ones(2, dtype=torch.float16)}],
    }  # fmt: skip
    buffer = io.BytesIO()
    torch.save(tree, buffer)
    read = torch_archive.load(buffer.getvalue())
    expected = torch.load(io.BytesIO(buffer.getvalue()), weights_only=True)
    for key in ("t", "slice", "count", "ints", "mask", "empty"):
        assert read[key].dtype == expected[key].numpy().dtype and read[key].flags.writeable
        np.testing.assert_array_equal(read[key], expected[key].numpy())
    assert read["nested"][:3] == [1, "a", (2.5, None)]
    np.testing.assert_array_equal(read["nested"][3]["k"], np.ones(2, np.float16))

    code = io.BytesIO()
    torch.save({"w": torch.zeros(2), "x": _Code()}, code)
    with pytest.raises(Exception, match="print is not allowed in a checkpoint"):
        torch_archive.load(code.getvalue())
    numbered = io.BytesIO()
    torch.save({"w": torch.zeros(2), "by number": {3: torch.ones(1)}}, numbered)
    with pytest.raises(ValueError, match="a key int"):  # plain data: string keys
        torch_archive.load(numbered.getvalue())
    past = io.BytesIO()
    torch.save(torch.zeros(4)[2:], past)
    forged = io.BytesIO()
    with zipfile.ZipFile(past) as archive, zipfile.ZipFile(forged, "w") as copy:
        for name in archive.namelist():
            data = archive.read(name)
            if name.endswith("data.pkl"):  # the view at offset 2: size 2 -> 9
                assert b"K\x02K\x02\x85" in data
                data = data.replace(b"K\x02K\x02\x85", b"K\x02K\x09\x85")
            copy.writestr(name, data)
    with pytest.raises(ValueError, match="reaches past its storage"):
        torch_archive.load(forged.getvalue())
    with pytest.raises(Exception):  # noqa: B017 - any error: these bytes are no archive
        torch_archive.load(b"PK\x03\x04 not a zip")


def _samples(aux: torch.Tensor, action_dim: int) -> Samples:
    """The columns of a fused minibatch's `aux` (`FusedActorCritic.step`) as `Samples`."""
    return Samples(aux[:, :action_dim], *aux[:, action_dim:].T)


@pytest.mark.parametrize(
    ("spaces", "flat"),
    [
        (DERL_OBS, slice(None, None, 3)),
        (DERL_OBS, slice(None)),
        ({"proprioception": 50}, slice(0)),
    ],
    ids=["heightmap-some-flat", "heightmap-all-flat", "proprioception-only"],
)
def test_fused_network_matches_torch_and_autograd(spaces: dict[str, int], flat: slice) -> None:
    """Sampling, values and the hand-written PPO loss and gradient equal torch's on the loss as
    defined (`ppo_loss`, autograd), with some or all heightmap rows zero (flat ground, which the
    first layer skips), and with proprioception alone (no fuse layer)."""
    torch.manual_seed(0)
    rows, a = 64, 12
    net = ActorCritic(spaces, a)
    with torch.no_grad():
        net.log_std.copy_(torch.linspace(-1.0, 0.5, a))
        for p in net.parameters():  # biases away from their zero init, so their gradients count
            p.add_(0.05 * torch.randn_like(p))
    fused = FusedActorCritic(net, lr=3e-4, adam_eps=1e-5)
    obs = {k: torch.randn(rows, d) for k, d in spaces.items()}
    if "heightmap" in obs:
        obs["heightmap"][flat] = 0.0

    noise = np.random.default_rng(0).standard_normal((rows, a), dtype=np.float32)
    actions = np.empty_like(noise)
    fused.begin_sampling()
    fused.act({k: v.numpy() for k, v in obs.items()}, noise, actions)
    with torch.no_grad():
        mean = net.action_mean(obs)
        pi = torch.distributions.Normal(mean, net.log_std.exp())
        expected = mean + net.log_std.exp() * torch.from_numpy(noise)
        torch.testing.assert_close(torch.from_numpy(actions), expected, atol=1e-5, rtol=1e-5)
        log_prob = pi.log_prob(torch.from_numpy(actions)).sum(-1)
        torch.testing.assert_close(
            torch.from_numpy(fused.log_prob_of_noise(noise)), log_prob, atol=1e-4, rtol=1e-5
        )
        torch.testing.assert_close(
            torch.from_numpy(fused.values(obs)), net.value(obs), atol=1e-5, rtol=1e-5
        )

    # Old log-probs shifted so some ratios fall outside the clip range, both signs of advantage,
    # old values far enough for the value clip to bite on some rows.
    gen = torch.Generator().manual_seed(1)
    aux = torch.cat(
        [
            torch.from_numpy(actions),
            (log_prob + 0.4 * torch.randn(rows, generator=gen))[:, None],
            torch.randn(rows, 1, generator=gen),
            (net.value(obs).detach() + 0.5 * torch.randn(rows, generator=gen))[:, None],
            torch.randn(rows, 1, generator=gen),
        ],
        1,
    )
    coef = PPOCoefficients(
        clip=0.2, value_clip=0.2, value_coef=0.5, entropy_coef=0.01, max_grad_norm=1e9, kl_stop=1e9
    )
    net.zero_grad()
    loss = ppo_loss(net, obs, _samples(aux, a), coef)
    loss.total.backward()
    mb = fused.minibatch(rows, [spaces[k] for k in fused.keys], aux.shape[1])
    sources = [obs[k] for k in fused.keys]
    mb.gather(sources, fused.nonzero_rows(obs), aux, torch.randperm(rows, generator=gen))
    flat_rows = len(range(rows)[flat])
    expected_at = [rows - flat_rows, None] if "heightmap" in obs else [None]
    assert [None if at is None else len(at) for at in mb.at] == expected_at
    mb.gather(sources, fused.nonzero_rows(obs), aux, torch.arange(rows))
    assert fused.step(mb, coef)  # the gradient stays in fused.grad after the Adam step
    # the diagnostics: the loss's terms as the step computed them on the way to its gradient
    assert fused.losses.steps == 1 and 0 < loss.clip_fraction < 1
    policy, value, kl, clipped = fused.losses.means()
    assert policy == pytest.approx(loss.policy.item(), rel=1e-4, abs=1e-6)
    assert value == pytest.approx(loss.value.item(), rel=1e-4)
    assert kl == pytest.approx(loss.approx_kl.item(), rel=1e-4, abs=1e-6)
    assert clipped == loss.clip_fraction.item()
    flat = torch.cat(
        [
            g
            for layer in fused.actor.layers + fused.critic.layers
            for g in (layer.module.weight.grad.T.reshape(-1), layer.module.bias.grad)
        ]
        + [net.log_std.grad]
    )
    torch.testing.assert_close(fused.grad, flat, atol=2e-6, rtol=1e-4)
    before = {name: p.detach().clone() for name, p in net.named_parameters()}
    fused.store_into_net()  # the step moved every parameter, and the net receives it
    still = {name for name, p in net.named_parameters() if torch.equal(before[name], p)}
    # (all rows flat: the heightmap's first weights have no gradient)
    assert still == (
        {f"{tower}.branches.heightmap.0.weight" for tower in ("actor", "critic")}
        if flat_rows == rows and "heightmap" in obs
        else set()
    )


def test_a_minibatch_beyond_the_kl_limit_stops_the_update() -> None:
    """The released code's `train_on_batch`: before each minibatch's step, the approximate KL
    mean(old log-prob - log-prob) over the minibatch; above KL_TARGET_COEF x 0.01 = 0.2 the
    update ends without that step."""
    torch.manual_seed(0)
    rows, a = 64, 3
    obs_spaces = {"proprioception": 5}
    fused = FusedActorCritic(ActorCritic(obs_spaces, a), lr=3e-4, adam_eps=1e-5)
    obs = {"proprioception": torch.randn(rows, 5)}
    noise = np.random.default_rng(0).standard_normal((rows, a), dtype=np.float32)
    actions = np.empty_like(noise)
    fused.begin_sampling()
    fused.act({"proprioception": obs["proprioception"].numpy()}, noise, actions)
    log_prob = torch.from_numpy(fused.log_prob_of_noise(noise))
    coef = PPOCoefficients(
        clip=0.2, value_clip=0.2, value_coef=0.5, entropy_coef=0.01, max_grad_norm=0.5, kl_stop=0.2
    )
    mb = fused.minibatch(rows, [5], a + 4)
    for shift, steps in ((0.25, False), (0.15, True)):  # the KL is the old log-prob's excess
        aux = torch.cat(
            [torch.from_numpy(actions), (log_prob + shift)[:, None], torch.randn(rows, 3)], 1
        )
        mb.gather([obs["proprioception"]], [None], aux, torch.arange(rows))
        before = fused.theta.clone()
        assert fused.step(mb, coef) is steps
        assert torch.equal(fused.theta, before) is not steps
    assert PPOConfig().kl_stop == 0.2


def test_value_gradient_where_the_clipped_term_wins_by_rounding() -> None:
    """Within the value clip the clipped term equals the unclipped one, but in float32
    v_old + (v - v_old) need not round back to v: where the clipped term comes out larger, the
    max passes its gradient (autograd's), which the hand-written gradient had dropped."""
    torch.manual_seed(0)
    rows, spaces = 512, {"proprioception": 7}
    net = ActorCritic(spaces, 2)
    fused = FusedActorCritic(net, lr=3e-4, adam_eps=1e-5)
    obs = {"proprioception": torch.randn(rows, 7)}
    gen = torch.Generator().manual_seed(1)
    value = net.value(obs).detach()
    old_value = value + 0.1 * torch.randn(rows, generator=gen)  # every row within the clip
    actions = net.action_mean(obs).detach()
    old_log_prob = torch.distributions.Normal(actions, 1.0).log_prob(actions).sum(-1)
    aux = torch.cat([actions, old_log_prob[:, None], torch.zeros(rows, 1), old_value[:, None]], 1)
    aux = torch.cat([aux, torch.randn(rows, 1, generator=gen)], 1)
    coef = PPOCoefficients(
        clip=0.2, value_clip=0.2, value_coef=0.5, entropy_coef=0.0, max_grad_norm=1e9, kl_stop=1e9
    )
    net.zero_grad()
    ppo_loss(net, obs, _samples(aux, 2), coef).total.backward()
    mb = fused.minibatch(rows, [7], aux.shape[1])
    mb.gather([obs["proprioception"]], [None], aux, torch.arange(rows))
    fused.step(mb, coef)
    torch.testing.assert_close(fused.critic.head.gb, net.value_head.bias.grad, atol=1e-7, rtol=1e-5)


def test_fused_adam_steps_as_torch_optim_adam() -> None:
    """The directly called kernel moves the parameters exactly as `torch.optim.Adam` does,
    through steps with different gradients and a changed learning rate."""
    torch.manual_seed(0)
    fused = FusedActorCritic(ActorCritic(DERL_OBS, 5), lr=3e-4, adam_eps=1e-5)
    theta = fused.theta.detach().clone().requires_grad_()
    reference = torch.optim.Adam([theta], lr=3e-4, eps=1e-5, fused=True)
    for step in range(3):
        if step == 2:
            fused.set_lr(1e-4)
            reference.param_groups[0]["lr"] = 1e-4
        fused.grad.copy_(torch.randn_like(fused.grad))
        theta.grad = fused.grad.clone()
        fused.adam.step()
        reference.step()
        torch.testing.assert_close(fused.theta, theta.detach(), atol=0, rtol=0)


def test_running_mean_std_matches_numpy_and_round_trips() -> None:
    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 2.0, (n, 5)) for n in (1, 17, 64)]
    rms = RunningMeanStd((5,))
    for batch in batches:
        rms.update(batch)
    everything = np.concatenate(batches)
    np.testing.assert_allclose(rms.mean, everything.mean(0), rtol=1e-12)
    np.testing.assert_allclose(rms.var, everything.var(0), rtol=1e-12)
    assert rms.count == len(everything)

    spaces = {"proprioception": 5, "heightmap": 3}
    norm = ObsNormalizer(spaces, clip=10.0)
    obs = {
        "proprioception": everything.astype(np.float32),
        "heightmap": rng.normal(size=(82, 3)).astype(np.float32),
    }
    norm.update(obs)
    out = norm.normalize(obs)
    expected = np.clip(
        (everything - everything.mean(0)) / np.sqrt(everything.var(0) + 1e-8), -10, 10
    )
    np.testing.assert_allclose(out["proprioception"], expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(out["heightmap"], obs["heightmap"])
    assert set(norm.state_dict()) == {f"proprioception/{k}" for k in ("mean", "var", "count")}

    loaded = ObsNormalizer(spaces, clip=10.0)
    loaded.load_state_dict(norm.state_dict())
    for key in obs:
        np.testing.assert_array_equal(loaded.normalize(obs)[key], out[key])


def test_flat_start_heightmap_then_terrain_reaches_the_network_raw() -> None:
    # A body on the flat start area sees a heightmap of exact zeros for many steps; normalising
    # it would turn the first obstacle into saturated +/-10 inputs. Only proprioception is.
    rng = np.random.default_rng(0)
    norm = ObsNormalizer(DERL_OBS, clip=10.0)
    out = {}
    for step in range(600):
        heights = np.zeros((32, 1410), np.float32)
        if step >= 500:
            heights[:] = rng.uniform(-0.4, 0.6, heights.shape)
        obs = {"proprioception": rng.normal(size=(32, 50)).astype(np.float32), "heightmap": heights}
        norm.update(obs)
        out = norm.normalize(obs, out=out or None)
        np.testing.assert_array_equal(out["heightmap"], heights)
    assert np.abs(out["heightmap"]).max() <= 0.6
    assert np.abs(out["proprioception"]).max() < 10.0


def test_reward_scaler_divides_by_return_std_and_round_trips() -> None:
    scaler = RewardScaler(num_envs=2, gamma=0.5, clip=10.0)
    rewards = [np.array([1.0, 2.0]), np.array([1.0, 2.0]), np.array([1.0, 2.0])]
    done = [np.array([False, True]), np.array([False, False]), np.array([False, False])]
    returns_seen = []
    running = np.zeros(2)
    for reward, d in zip(rewards, done, strict=True):
        running = running * 0.5 + reward
        returns_seen.append(running.copy())
        running[d] = 0.0
        scaled = scaler.scale(reward, d)
    std = np.sqrt(np.concatenate(returns_seen).var() + 1e-8)
    np.testing.assert_allclose(scaled, rewards[-1] / std)

    copy = RewardScaler(num_envs=2, gamma=0.5, clip=10.0)
    copy.load_state_dict(scaler.state_dict())
    np.testing.assert_array_equal(copy.stats.var, scaler.stats.var)


def test_fitness_window_and_fallbacks() -> None:
    """The released code's fitness: the mean of the per-iteration values (the mean of the last
    `recent` finished episodes, once two have finished) in the window; before that, the one
    finished episode, or the running partial sums."""
    tracker = EpisodeTracker(num_envs=2, component="forward", recent=2)
    no, first, both = np.array([False, False]), np.array([True, False]), np.array([True, True])
    tracker.step(np.ones(2), {"forward": np.array([1.0, 2.0])}, no, env_steps=2)
    assert tracker.end_iteration(2) is None
    unfinished = tracker.fitness(2, window=10)
    assert (unfinished.value, unfinished.source, unfinished.episodes) == (1.5, "unfinished", 0)
    tracker.step(np.ones(2), {"forward": np.array([1.0, 2.0])}, first, env_steps=4)
    assert tracker.end_iteration(4) is None  # one episode: no curve point yet
    single = tracker.fitness(4, window=10)
    assert (single.value, single.source, single.episodes) == (2.0, "last_episodes", 1)
    tracker.step(np.ones(2), {"forward": np.array([5.0, 2.0])}, both, env_steps=100)
    assert tracker.end_iteration(100) == 5.5  # episodes 5 and 6 (recent=2)
    tracker.step(np.ones(2), {"forward": np.array([0.0, 1.0])}, np.array([False, True]), 200)
    assert tracker.end_iteration(200) == 3.5  # episodes 6 and 1
    log = tracker.log()
    np.testing.assert_array_equal(log.finish_step, [4, 100, 100, 200])
    np.testing.assert_array_equal(log.components["forward"], [2.0, 5.0, 6.0, 1.0])
    np.testing.assert_array_equal(log.length, [2, 1, 3, 1])
    assert tracker.curve == [(100, 5.5), (200, 3.5)]
    last = tracker.fitness(200, window=50)
    assert (last.value, last.source, last.episodes) == (3.5, "window", 2)
    both_points = tracker.fitness(200, window=150)
    assert (both_points.value, both_points.source, both_points.episodes) == (4.5, "window", 3)


def test_checkpoint_bytes_give_identical_actions() -> None:
    torch.manual_seed(0)
    net = ActorCritic(DERL_OBS, 12)
    norm = ObsNormalizer(DERL_OBS, clip=10.0)
    rng = np.random.default_rng(0)
    obs = {k: rng.normal(2.0, 3.0, (16, d)).astype(np.float32) for k, d in DERL_OBS.items()}
    norm.update(obs)
    config = PPOConfig(fitness_component="forward")
    data = Checkpoint.capture(net, norm, config).to_bytes()
    restored = Checkpoint.from_bytes(data)
    assert restored.config == config and restored.obs_spaces == DERL_OBS
    actions = Policy(net, norm)(obs)
    assert actions.shape == (16, 12) and actions.dtype == np.float32
    np.testing.assert_array_equal(Policy.from_checkpoint(data)(obs), actions)
    np.testing.assert_array_equal(Policy.from_checkpoint(restored)(obs), actions)

    old = torch.load(io.BytesIO(data), weights_only=True)
    del old["format"]  # format 1 had no version field (and normalised every type)
    buffer = io.BytesIO()
    torch.save(old, buffer)
    with pytest.raises(ValueError, match="checkpoint format 1"):
        Checkpoint.from_bytes(buffer.getvalue())
    old["format"] = 2  # a proprioception-only network had a fuse layer
    buffer = io.BytesIO()
    torch.save(old, buffer)
    with pytest.raises(ValueError, match="format 2 gave a network of one observation type"):
        Checkpoint.from_bytes(buffer.getvalue())


def test_gym_adapter_autoresets_and_reports_truncation() -> None:
    env = GymBatchedEnv("InvertedPendulum-v5", 3, max_episode_steps=5)
    assert isinstance(env, BatchedEnv)
    assert env.obs_spaces == {"proprioception": 4} and env.action_dim == 1
    obs = env.reset(seed=7)["proprioception"]
    assert obs.shape == (3, 4) and obs.dtype == np.float32
    np.testing.assert_array_equal(env.reset(seed=7)["proprioception"], obs)
    for _ in range(5):
        step = env.step(np.zeros((3, 1), np.float32))
    assert step.truncated.all() and not step.terminated.any()
    assert not env.step(np.zeros((3, 1), np.float32)).truncated.any()  # new episodes
    np.testing.assert_array_equal(step.components["reward"], step.reward)
    env.close()


def _short_run(seed: int, **options: object) -> tuple[TrainResult, list[Progress]]:
    env = GymBatchedEnv("InvertedPendulum-v5", 4)
    config = PPOConfig(
        num_envs=4,
        rollout_steps=64,
        total_steps=512,
        minibatch_size=64,
        fitness_component="reward",
        seed=seed,
        **options,
    )
    progress = []
    result = train(env, config, callback=progress.append)
    env.close()
    return result, progress


def test_training_is_reproducible() -> None:
    first, progress = _short_run(seed=3)
    second, _ = _short_run(seed=3)
    assert [p.iteration for p in progress] == [1, 2]
    assert first.env_steps == 512 and len(first.curve) == 2
    assert first.curve == second.curve
    assert len(first.episodes) == len(second.episodes) > 0
    assert first.time_split.physics_s is None  # the gymnasium adapter does not count it
    assert first.kl_stops == 0
    stopped, _ = _short_run(seed=3, kl_stop=1e-12)  # every update stops at once
    assert stopped.kl_stops == 2
    assert stopped.curve != first.curve
    for key, value in first.checkpoint.weights.items():
        assert torch.equal(value, second.checkpoint.weights[key]), key


@pytest.mark.slow
def test_ppo_learns_inverted_pendulum() -> None:
    env = GymBatchedEnv("InvertedPendulum-v5", 32)
    # The paper's hyperparameters unchanged, only a smaller budget and fitness window.
    config = PPOConfig(total_steps=250_000, fitness_component="reward", fitness_window_steps=20_000)
    result = train(env, config)
    env.close()
    assert result.env_steps == 249_856  # 61 whole rollouts of 32 x 128
    assert result.fitness_source == "window"
    assert result.fitness >= 900.0, result.curve[-10:]
    assert result.curve[-1][1] >= 900.0
    assert result.wall_time_s < 240.0
