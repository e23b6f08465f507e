"""derl from Python as a gymnasium user meets it: `import derl` registers every task (without
importing the simulation) with its episode length, the environments render RGB frames for
gymnasium's video wrappers, flatten for a learner of one array (Stable-Baselines3's MlpPolicy),
and come as a vector environment of copies in one batch; a trained body loads and acts in a few
lines, in the environment `gymnasium.make` makes; the version is the package's."""

from __future__ import annotations

import importlib.metadata
import json
import os
import subprocess
import sys
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers import FlattenObservation, RenderCollection
from nodes_fixtures import REPO, derl_argv

import derl
from derl.envs import TASKS, EnvConfig, make_task
from derl.lifetime import learn, ppo_config
from derl.unimal import Genome

REGISTERED = """
import sys, gymnasium, derl
assert "derl.envs" not in sys.modules  # registered, not yet imported
env = gymnasium.make("derl/FT-v0", genome=sys.argv[1])
obs, _ = env.reset(seed=0)
print(sorted(obs), env.action_space.shape[0])
"""


def test_import_derl_registers_every_task_with_gymnasium(quadruped: Genome, tmp_path: Path) -> None:
    assert {make_task(name).gym_name: name for name in TASKS} == derl.GYM_TASKS
    genome = tmp_path / "body.json"
    genome.write_text(quadruped.model_dump_json())
    made = subprocess.run([sys.executable, "-c", REGISTERED, str(genome)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert made.returncode == 0, made.stderr
    assert made.stdout.split() == ["['proprioception']", "10"]


def test_the_registered_episode_length_is_the_simulations() -> None:
    assert gymnasium.spec("derl/FT-v0").max_episode_steps == EnvConfig().episode_steps
    assert EnvConfig().episode_steps == derl.GYM_EPISODE_STEPS


def test_a_flattened_observation_for_a_learner_of_one_array(quadruped: Genome) -> None:
    """What Stable-Baselines3's MlpPolicy takes (the README trains it so: slow)."""
    env = FlattenObservation(gymnasium.make("derl/VT-v0", genome=quadruped))
    assert isinstance(env.observation_space, gymnasium.spaces.Box)
    obs, _ = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape and obs.dtype == np.float32


def test_copies_in_one_batch_as_a_gymnasium_vector_env(quadruped: Genome) -> None:
    """`make_vec` of the vector entry point: (N, dim) observations; an episode that ends (here
    after 3 steps) starts again in the same step, its last observation in the info."""
    env = gymnasium.make_vec("derl/FT-v0", num_envs=3, vectorization_mode="vector_entry_point",
                             genome=quadruped, max_episode_steps=3)  # fmt: skip
    assert env.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    first, _ = env.reset(seed=0)
    again, _ = env.reset(seed=0)
    np.testing.assert_array_equal(first["proprioception"], again["proprioception"])
    single = env.single_observation_space["proprioception"]
    assert first["proprioception"].shape == (3, *single.shape)
    actions = np.zeros(env.action_space.shape, np.float32)
    for _ in range(2):
        _, reward, _, _, info = env.step(actions)
        assert reward.shape == (3,) and info["forward"].shape == (3,) and "final_obs" not in info
    obs, _, _, truncated, info = env.step(actions)
    assert truncated.all() and info["_final_obs"].all()
    assert not np.array_equal(info["final_obs"][0]["proprioception"], obs["proprioception"][0])
    env.close()


def test_rgb_frames_for_gymnasiums_video_wrappers(quadruped: Genome) -> None:
    env = gymnasium.make("derl/VT-v0", genome=quadruped, render_mode="rgb_array", width=64,
                         height=48)  # fmt: skip
    assert env.metadata["render_fps"] == 50  # one frame a control step: real time
    recorded = RenderCollection(env)  # what RecordVideo films (it writes them with moviepy)
    recorded.reset(seed=0)
    for _ in range(3):
        recorded.step(recorded.action_space.sample())
    frames = recorded.render()
    assert len(frames) == 4 and frames[0].shape == (48, 64, 3) and frames[0].dtype == np.uint8
    assert frames[-1].std() > 0  # a picture, not a blank
    recorded.close()
    plain = gymnasium.make("derl/FT-v0", genome=quadruped)
    plain.reset(seed=0)
    assert plain.render() is None
    plain.close()


def test_a_trained_body_loads_and_acts(quadruped: Genome, tmp_path: Path) -> None:
    _, result = learn(quadruped, "ft", ppo_config("ft", 1024, seed=0, num_envs=8))
    (tmp_path / "genome.json").write_text(quadruped.model_dump_json())
    (tmp_path / "checkpoint.pt").write_bytes(result.checkpoint.to_bytes())
    (tmp_path / "result.json").write_text(json.dumps({"task": "ft"}))
    agent = derl.load_trained(tmp_path)
    env = agent.gym_env()
    assert str(env) == str(gymnasium.make("derl/FT-v0", genome=quadruped))  # the same wrappers
    obs, _ = env.reset(seed=0)
    action = agent.act(obs)
    assert action.shape == env.action_space.shape and np.abs(action).max() <= 1.0
    batch = {key: np.stack([value, value]) for key, value in obs.items()}
    np.testing.assert_allclose(agent.act(batch), np.stack([action, action]), atol=1e-6)
    for _ in range(5):
        obs, reward, _, _, info = env.step(agent.act(obs))
    assert "forward" in info and isinstance(reward, float)
    env.close()


def test_the_version_is_the_packages() -> None:
    assert derl.__version__ == importlib.metadata.version("derl")
    shown = subprocess.run(derl_argv("--version"), capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0 and shown.stdout.strip() == f"derl {derl.__version__}"


@pytest.mark.slow
def test_stable_baselines3_trains_a_derl_body(quadruped: Genome, tmp_path: Path) -> None:
    pytest.importorskip("stable_baselines3")
    genome = tmp_path / "body.json"
    genome.write_text(quadruped.model_dump_json())
    example = REPO / "examples" / "stable_baselines3_ft.py"
    env = {**os.environ, "SB3_LOGDIR": str(tmp_path)}  # SB3's logger's folder, else in /tmp
    done = subprocess.run([sys.executable, str(example), str(genome), "2048"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "trained 2,048 steps: an episode walked" in done.stdout
    assert (tmp_path / "ppo_derl_ft.zip").is_file()
