"""`derl train` and `derl rollout`: learn a controller for one body, and replay what was learnt."""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

from derl.nodes.cli.options import at_least_one, fail
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from derl.replay import CHECKPOINT, EPISODE_STEPS, GENOME, RESULT
from derl.validation import problems

console = Console()

CURVE_CSV, CURVE_PNG = "curve.csv", "curve.png"
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

    rollout = commands.add_parser(
        "rollout",
        help="replay a trained policy deterministically",
        description="Replay the trained body of DIR: the output folder of `derl train`, or a "
        "run's best/NN-agent folder (the body is replayed in the task it was trained in).",
    )
    rollout.add_argument("dir", type=Path, help="folder with genome.json and checkpoint.pt")
    rollout.add_argument("--episodes", type=at_least_one, default=3)
    rollout.add_argument("--seed", type=int, default=0)
    rollout.add_argument(
        "--episode-steps",
        type=at_least_one,
        default=EPISODE_STEPS,
        metavar="N",
        help=f"end an episode after N control steps of 20 ms (default {EPISODE_STEPS})",
    )
    rollout.add_argument("--video", type=Path, help="write a video (.mp4 or .gif) of episode 1")
    rollout.add_argument(
        "--video-size",
        type=_frame_size,
        default=(480, 360),
        metavar="WxH",
        help="the video's frame size in pixels (default 480x360)",
    )
    rollout.add_argument(
        "--video-every",
        type=at_least_one,
        default=1,
        metavar="N",
        help="keep every Nth control step's frame (default 1: half speed; 2: real time)",
    )
    rollout.set_defaults(handler=_rollout)


def _frame_size(text: str) -> tuple[int, int]:
    """'320x240' -> (320, 240)."""
    width, _, height = text.lower().partition("x")
    if not (width.isdigit() and height.isdigit() and min(int(width), int(height)) >= 16):
        raise argparse.ArgumentTypeError(f"{text!r}: give WIDTHxHEIGHT in pixels, e.g. 320x240")
    return int(width), int(height)


def _train(args: argparse.Namespace) -> int:
    from derl.nodes.cli.unimal import load_genome
    from pydantic import ValidationError

    from derl.lifetime import learn, ppo_config

    genome = load_genome(args.genome)
    try:
        config = ppo_config(args.task, args.steps, args.seed, num_envs=args.envs)
    except ValidationError as error:
        fail(f"cannot train with these settings: {problems(error, FLAGS)}")
    trained = config.iterations * config.batch_size
    if trained != args.steps:  # PPO updates after whole rollouts, as the released code does
        console.print(
            f"training {trained:,} env steps: --steps {args.steps} rounded down to whole "
            f"rollouts ({config.iterations} of {config.batch_size:,} = {config.num_envs} copies "
            f"x {config.rollout_steps} steps)",
            highlight=False,
            soft_wrap=True,
        )
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
        job = bar.add_task(f"{args.task}", total=trained, ret="-", sps=0)

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
    from derl.envs.video import write_video
    from derl.replay import NotTrained, Trained, play

    try:
        trained = Trained.load(args.dir)
    except NotTrained as error:
        fail(str(error), code=2)
    film = args.video_size if args.video else None
    for number, episode in enumerate(
        play(trained, args.episodes, args.seed, args.episode_steps, film, args.video_every),
        start=1,
    ):
        end = "fell/ended" if episode.fell else "time limit"
        console.print(
            f"episode {number}: {episode.component} {episode.total:.1f} over {episode.steps} "
            f"steps ({end})"
        )
        if number == 1 and args.video:
            try:
                write_video(args.video, episode.frames)
            except OSError as error:
                fail(str(error))
            console.print(f"wrote {args.video} ({len(episode.frames)} frames)")
    return 0
