"""`derl train` and `derl rollout`: learn a controller for one body, and replay what was learnt."""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from nodes.cli.options import at_least_one, fail, problems

console = Console()

GENOME, CHECKPOINT, RESULT, CURVE_CSV, CURVE_PNG = (
    "genome.json",
    "checkpoint.pt",
    "result.json",
    "curve.csv",
    "curve.png",
)
FLAGS = {"total_steps": "--steps", "num_envs": "--envs", "seed": "--seed"}  # PPOConfig's


def register(commands: argparse._SubParsersAction) -> None:
    from derl.envs import TASKS

    train = commands.add_parser("train", help="train a controller for one body with PPO")
    train.add_argument("--genome", type=Path, required=True, help="genome JSON file")
    train.add_argument("--task", choices=sorted(TASKS), default="ft")
    train.add_argument(
        "--steps", type=at_least_one, default=1_000_000, help="env steps (paper: 5M)"
    )
    train.add_argument("--seed", type=int, default=1409, help="training seed (paper's: 1409)")
    train.add_argument("--envs", type=at_least_one, default=32, help="env copies (paper: 32)")
    train.add_argument("--threads", type=at_least_one, default=1, help="simulation threads")
    train.add_argument("--out", type=Path, required=True, help="output directory")
    train.set_defaults(handler=_train)

    rollout = commands.add_parser("rollout", help="replay a trained policy deterministically")
    rollout.add_argument("dir", type=Path, help="output directory of `derl train`")
    rollout.add_argument("--episodes", type=at_least_one, default=3)
    rollout.add_argument("--seed", type=int, default=0)
    rollout.add_argument("--video", type=Path, help="write a video (.mp4 or .gif) of episode 1")
    rollout.set_defaults(handler=_rollout)


def _train(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from derl.lifetime import learn, ppo_config
    from nodes.cli.unimal import load_genome

    genome = load_genome(args.genome)
    try:
        config = ppo_config(args.task, args.steps, args.seed, num_envs=args.envs)
    except ValidationError as error:
        fail(f"cannot train with these settings: {problems(error, FLAGS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / GENOME).write_text(genome.model_dump_json(indent=2) + "\n")
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:,.0f}/{task.total:,.0f} steps"),
        TextColumn("return {task.fields[ret]}"),
        TextColumn("{task.fields[sps]:,.0f} steps/s"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=console) as bar:
        job = bar.add_task(
            f"{args.task}", total=config.iterations * config.batch_size, ret="-", sps=0
        )

        def show(progress) -> None:  # derl.rl.Progress
            ret = "-" if progress.recent_return is None else f"{progress.recent_return:.1f}"
            bar.update(job, completed=progress.env_steps, ret=ret, sps=progress.steps_per_second)

        summary, result = learn(genome, args.task, config, show, nthread=args.threads)
    (args.out / CHECKPOINT).write_bytes(result.checkpoint.to_bytes())
    (args.out / RESULT).write_text(
        json.dumps({"config": config.model_dump(), **summary.model_dump()}, indent=2) + "\n"
    )
    _write_curve(args.out, summary.curve_steps, summary.curve_returns, args.task)
    console.print(
        f"fitness {summary.fitness:.1f} ({summary.fitness_episodes} episodes), "
        f"cost of work {summary.cost_of_work:.3g}, {summary.steps_per_second:,.0f} steps/s, "
        f"{summary.wall_time_s:.0f} s -> {args.out}"
    )
    return 0


def _write_curve(out: Path, steps: list[int], returns: list[float], task: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with (out / CURVE_CSV).open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["env_steps", "mean_return"])
        writer.writerows(zip(steps, returns, strict=True))
    figure, axis = plt.subplots(figsize=(6, 3.5))
    axis.plot(steps, returns)
    axis.set(xlabel="environment steps", ylabel="mean episode return (fitness term)", title=task)
    axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(out / CURVE_PNG, dpi=120)
    plt.close(figure)


def _rollout(args: argparse.Namespace) -> int:
    import numpy as np

    from derl.envs import make_env
    from derl.rl import Policy
    from nodes.cli.unimal import load_genome

    try:
        result = json.loads((args.dir / RESULT).read_text())
        policy = Policy.from_checkpoint((args.dir / CHECKPOINT).read_bytes())
    except (OSError, ValueError) as error:
        raise SystemExit(f"derl: {args.dir} holds no finished training: {error}") from None
    task = result["task"]
    env = make_env(load_genome(args.dir / GENOME), task, num_envs=1, seed=args.seed)
    component = env.task.fitness_component
    recorder = _recorder(env) if args.video else None
    frames = []
    obs = env.reset(args.seed)
    for episode in range(1, args.episodes + 1):
        total, steps = 0.0, 0
        while True:
            if recorder is not None and episode == 1:
                frames.append(recorder.frame())
            step = env.step(policy(obs))
            obs, total, steps = step.obs, total + float(step.components[component][0]), steps + 1
            if step.terminated[0] or step.truncated[0]:
                break
        end = "fell/ended" if step.terminated[0] else "time limit"
        console.print(f"episode {episode}: {component} {total:.1f} over {steps} steps ({end})")
    if recorder is not None:
        _write_video(args.video, np.stack(frames))
        console.print(f"wrote {args.video} ({len(frames)} frames)")
    return 0


def _recorder(env):  # -> FrameRecorder
    from derl.envs.video import FrameRecorder

    return FrameRecorder(env)


def _write_video(path: Path, frames) -> None:
    import imageio.v3 as iio

    fps = 50 // 2  # every control step is 20 ms; play at half speed
    try:
        iio.imwrite(path, frames, fps=fps) if path.suffix != ".gif" else iio.imwrite(
            path, frames, duration=1000 / fps, loop=0
        )
    except (ImportError, ValueError, OSError) as error:
        raise SystemExit(
            f"derl: cannot write {path}: {error}. For .mp4 install imageio-ffmpeg "
            "(pip install 'derl[video]'), or ask for a .gif"
        ) from None
