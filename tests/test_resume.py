"""A training stopped and resumed ends with the bits of one never stopped: in the library (FT,
VT's terrains, MVT's sleeping box), and from the command line, where SIGTERM (Slurm's
preemption) saves the checkpoint, the curve with each iteration's PPO diagnostics and the result
so far, says in one line how to go on and exits 130, and `derl train --resume DIR` goes on; the
diagnostics also go to TensorBoard, and progress reaches a log file as plain timestamped
lines."""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import re
import signal
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
from nodes_fixtures import derl_argv
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.lifetime import learn, ppo_config
from derl.rl import snapshot
from derl.rl.checkpoint import state_from_bytes, state_to_bytes
from derl.unimal import Genome, sample_population

ENVS, ITERATIONS = 8, 6
STEPS = ENVS * 128 * ITERATIONS


def _bits(result) -> tuple[str, str]:  # derl.rl.TrainResult
    return result.fitness.hex(), hashlib.sha256(result.checkpoint.to_bytes()).hexdigest()


@pytest.mark.parametrize(
    "task",
    ["ft", pytest.param("vt", marks=pytest.mark.slow), pytest.param("mvt", marks=pytest.mark.slow)],
)
def test_a_training_stopped_and_resumed_ends_with_the_bits_of_one_never_stopped(task: str) -> None:
    (genome,) = sample_population(1, np.random.default_rng(5))
    config = ppo_config(task, STEPS, seed=1409, num_envs=ENVS)
    _, whole = learn(genome, task, config)
    states: list[tuple[int, bytes]] = []
    stopping = threading.Event()

    def stop_at_3(progress) -> None:  # derl.rl.Progress
        if progress.iteration == 3:
            stopping.set()

    _, part = learn(
        genome, task, config, stop_at_3, every=2, stop=stopping,
        save=lambda summary, result, state: states.append((result.iterations, state)),
    )  # fmt: skip
    assert [done for done, _ in states] == [2, 3] and part.iterations == 3
    summary, resumed = learn(genome, task, config, resume=states[-1][1])
    assert _bits(resumed) == _bits(whole)
    assert resumed.iterations == ITERATIONS and summary.env_steps == STEPS

    def kept(progress):  # derl.rl.Progress, but for its speed
        return dataclasses.replace(progress, steps_per_second=0.0)

    assert [kept(p) for p in resumed.progress] == [kept(p) for p in whole.progress]
    _, again = learn(genome, task, config, resume=states[0][1])  # an older state: the same end
    assert _bits(again) == _bits(whole)


def test_an_environment_restored_steps_on_exactly_even_with_sleeping_bodies() -> None:
    """MVT with MuJoCo's sleeping on (`EnvConfig.sleep`): boxes asleep and about to sleep are
    put back so (their countdowns are outside MuJoCo's state rows), and both copies step on to
    the bit."""
    (genome,) = sample_population(1, np.random.default_rng(5))
    rng = np.random.default_rng(0)

    def env(seed: int) -> UnimalEnv:
        made = UnimalEnv(genome, make_task("mvt"), EnvConfig(num_envs=ENVS, sleep=True), seed)
        made.reset(seed)
        return made

    def steps(target: UnimalEnv, count: int) -> np.ndarray:
        return np.array([target.step(rng.standard_normal((ENVS, target.action_dim),
                                                         dtype=np.float32)).reward
                         for _ in range(count)])  # fmt: skip

    first = env(3)
    steps(first, 60)  # boxes dropped at their resets: settling, about to sleep, asleep
    asleep = snapshot._sleep(first)
    assert asleep is not None and (asleep[0] >= 0).any()  # some box asleep
    assert snapshot.capturable(first)
    state = state_from_bytes(state_to_bytes({"env": snapshot.capture(first)}))["env"]
    noise = rng.bit_generator.state
    expected = steps(first, 200)
    second = env(99)
    snapshot.restore(second, state)
    rng.bit_generator.state = noise
    np.testing.assert_array_equal(steps(second, 200), expected)


@pytest.mark.slow
def test_derl_train_stops_on_sigterm_saving_everything_and_resumes(
    quadruped: Genome, tmp_path: Path
) -> None:
    genome = tmp_path / "body.json"
    genome.write_text(quadruped.model_dump_json())
    out, board = tmp_path / "body-ft", tmp_path / "tb"
    train = derl_argv("train", "--genome", str(genome), "--steps", str(STEPS), "--envs",
                      str(ENVS), "--out", str(out), "--tensorboard", str(board))  # fmt: skip
    with subprocess.Popen(train, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as run:
        assert run.stdout is not None
        first = run.stdout.readline()  # stdout is no terminal: a plain line per update, at first
        assert re.match(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d ft: [\d,]+/6,144 env steps", first)
        run.send_signal(signal.SIGTERM)
        stdout, stderr = run.communicate(timeout=120)
    assert run.returncode == 130, stderr
    assert "Traceback" not in stderr
    last = stdout.strip().splitlines()[-1]
    assert re.fullmatch(
        rf"stopped after iteration \d of {ITERATIONS} \([\d,]+ env steps\): checkpoint, curve "
        rf"and result in {out}; `derl train --resume {out}` goes on",
        last,
    ), stdout
    saved = json.loads((out / "result.json").read_text())
    assert not saved["finished"] and 1 <= saved["iterations"] < ITERATIONS
    assert (out / "checkpoint.pt").is_file() and (out / "training-state.pt").is_file()
    assert len(list(csv.reader((out / "curve.csv").open()))) == 1 + saved["iterations"]

    # TensorBoard where the first start wrote it, without being told again
    resumed = subprocess.run(derl_argv("train", "--resume", str(out)),
                             capture_output=True, text=True, timeout=300)  # fmt: skip
    assert resumed.returncode == 0, resumed.stderr

    _, whole = learn(quadruped, "ft", ppo_config("ft", STEPS, seed=1409, num_envs=ENVS))
    checkpoint = hashlib.sha256((out / "checkpoint.pt").read_bytes()).hexdigest()
    assert (whole.fitness.hex(), checkpoint) == _bits(whole)
    result = json.loads((out / "result.json").read_text())
    assert result["finished"] and result["fitness"] == whole.fitness
    rows = list(csv.DictReader((out / "curve.csv").open()))
    assert [int(row["iteration"]) for row in rows] == list(range(1, ITERATIONS + 1))
    for row, point in zip(rows, whole.progress, strict=True):
        assert float(row["policy_loss"]) == point.diagnostics.policy_loss
        assert float(row["explained_variance"]) == point.diagnostics.explained_variance
        assert 0.0 <= float(row["clip_fraction"]) <= 1.0 and float(row["steps_per_s"]) > 0

    events = EventAccumulator(str(board / out.name), size_guidance={"scalars": 0})
    events.Reload()
    steps = [event.step for event in events.Scalars("train/approx_kl")]
    assert steps == [point.env_steps for point in whole.progress]  # both processes', once each
    assert {"train/policy_loss", "train/value_loss", "train/entropy", "train/clip_fraction",
            "train/explained_variance", "train/learning_rate", "time/fps", "time/iterations",
            "rollout/fitness_term_mean", "rollout/ep_rew_mean", "rollout/ep_len_mean",
            "rollout/episodes"} <= set(events.Tags()["scalars"])  # fmt: skip
