"""Lifetime learning of UNIMALs: `derl train` / `derl rollout`, fitness bookkeeping, and proof
that PPO makes a fixed 4-legged body walk forward on flat terrain."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from derl.envs import make_env
from derl.lifetime import fitness_window, learn, ppo_config
from derl.unimal import Genome


def _random_policy_fitness(genome: Genome, episodes: int = 64) -> float:
    env = make_env(genome, "ft", num_envs=32, seed=0)
    env.reset(0)
    rng = np.random.default_rng(0)
    sums, running = [], np.zeros(32)
    while len(sums) < episodes:
        step = env.step(rng.uniform(-1, 1, (32, env.action_dim)).astype(np.float32))
        running += step.components["forward"]
        done = step.terminated | step.truncated
        sums.extend(running[done])
        running[done] = 0
    return float(np.mean(sums))


def test_fitness_window_scales_with_the_budget() -> None:
    # the released code's last 100 of its 1220 iterations, as a share of the training
    assert fitness_window(5_000_000, 4096) == 409_600  # the paper's budget: the code's window
    assert fitness_window(5_000_000, 2048) == 200 * 2048  # 2441 iterations: the last 200
    assert fitness_window(1_000_000, 4096) == 20 * 4096  # 244 iterations: the last 20
    assert fitness_window(300_000, 4096) == 6 * 4096  # 73 iterations: 6
    assert fitness_window(8192, 4096) == 4096  # at least one iteration
    assert ppo_config("ft", 1_000_000, seed=0).fitness_window_steps == 81_920
    config = ppo_config("mvt", 8192, seed=3)
    assert config.fitness_component == "manipulation" and config.seed == 3


def test_short_training_reports_everything(quadruped: Genome) -> None:
    config = ppo_config("vt", 8192, seed=0, num_envs=8, rollout_steps=128, minibatch_size=256)
    summary, result = learn(quadruped, "vt", config)
    assert summary.env_steps == 8192 and summary.episodes == len(result.episodes) > 0
    assert math.isfinite(summary.fitness) and summary.mass == pytest.approx(13.77, abs=0.01)
    assert summary.energy > 0
    assert len(summary.curve_steps) == len(summary.curve_returns) > 0
    split = summary.time_split
    assert set(split) == {"env_s", "inference_s", "update_s", "other_s", "physics_s"}
    assert 0 < split["physics_s"] < split["env_s"]  # MuJoCo's share of the environment's time
    again, _ = learn(quadruped, "vt", config)
    assert again.curve_returns == summary.curve_returns  # reproducible


def test_train_and_rollout_commands(quadruped: Genome, tmp_path: Path) -> None:
    genome = tmp_path / "body.json"
    genome.write_text(quadruped.model_dump_json())
    out = tmp_path / "run"
    command = [sys.executable, "-m", "derl.nodes.cli"]
    trained = subprocess.run(
        [*command, "train", "--genome", str(genome), "--task", "mvt", "--steps", "9000",
         "--envs", "16", "--out", str(out)],
        check=True, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    # 9,000 steps are 4 whole rollouts of 16 x 128 steps, and derl says so
    assert "training 8,192 env steps: --steps 9000 rounded down" in trained.stdout
    for name in ("genome.json", "checkpoint.pt", "result.json", "curve.csv", "curve.png"):
        assert (out / name).stat().st_size > 0
    result = json.loads((out / "result.json").read_text())
    assert result["task"] == "mvt" and result["config"]["fitness_component"] == "manipulation"
    assert result["env_steps"] == 8192
    rows = list(csv.reader((out / "curve.csv").open()))
    assert rows[0][:3] == ["iteration", "env_steps", "mean_return"] and len(rows) == 1 + 4
    assert rows[0][3:] == ["ep_rew_mean", "ep_len_mean", "episodes", "policy_loss", "value_loss",
                           "entropy", "approx_kl", "clip_fraction", "explained_variance",
                           "learning_rate", "minibatches", "steps_per_s"]  # fmt: skip
    assert result["finished"] and (out / "training-state.pt").is_file()  # what extends it
    video = tmp_path / "episode.gif"
    shown = subprocess.run(
        [*command, "rollout", str(out), "--episodes", "2", "--episode-steps", "100",
         "--video", str(video), "--video-size", "160x120", "--video-every", "2"],
        check=True, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert shown.stdout.count("episode ") == 2
    frames = iio.imread(video, index=None)  # every 2nd of episode 1's frames, at 160 x 120
    assert frames.shape[1:3] == (120, 160) and 0 < len(frames) <= 50


@pytest.mark.slow
def test_ppo_makes_a_quadruped_walk_forward(quadruped: Genome) -> None:
    random_fitness = _random_policy_fitness(quadruped)
    summary, _ = learn(quadruped, "ft", ppo_config("ft", 300_000, seed=1409))
    # Measured here: the random policy scores -10 (it falls backwards). After 300k steps, over
    # seeds 0-3 and 1409, the fitness (its last 10 iterations', `fitness_window`) was 6.4 to 19.2
    # (mean 11.2; this seed's 11.1; 25.6 to 50.0 after 500k, which took 1.8 times the CPU) and
    # the curve rose by 15 to 29 from its first iteration (this seed's 26). The bounds are half
    # the worst seed's: any seed passes where PPO learns as it does, and a policy that learns
    # nothing fails.
    assert random_fitness < 0
    assert summary.fitness > 3.0 and summary.fitness > random_fitness + 8.0
    assert summary.curve_returns[-1] > summary.curve_returns[0] + 7.5
