"""`derl train` and `derl rollout`: learn a controller for one body, and replay what was learnt.

`derl train` saves what it needs to resume every `--checkpoint-every` iterations and when it is
stopped (Ctrl-C, SIGTERM: Slurm's preemption): the policy (`checkpoint.pt`), the curve, the
result so far and the training's whole state (`training-state.pt`, `derl.rl.ppo`), then says in
one line how to go on; `derl train --resume DIR` goes on from there and ends with the bits of a
training never stopped. Each iteration's PPO diagnostics go to `curve.csv` and, with
`--tensorboard`, to TensorBoard.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import signal
import threading
from pathlib import Path
from typing import Any, ClassVar, TypedDict

from rich.progress import TextColumn

from derl.nodes.cli.options import at_least_one, fail, output_directory
from derl.nodes.cli.progress import Shown, output_console
from derl.replay import CHECKPOINT, EPISODE_STEPS, GENOME, RESULT
from derl.validation import problems

console = output_console()

CURVE_CSV, CURVE_PNG, STATE = "curve.csv", "curve.png", "training-state.pt"
FLAGS = {"total_steps": "--steps", "num_envs": "--envs", "seed": "--seed"}  # PPOConfig's


class _Defaults(TypedDict):
    task: str
    steps: int
    seed: int
    envs: int


DEFAULTS: _Defaults = {"task": "ft", "steps": 1_000_000, "seed": 1409, "envs": 32}
CHECKPOINT_EVERY = 100
"""Iterations between two saves of a training's state (4,096 env steps each by default)."""
STOPPED = 130
"""The exit status of a training stopped by a signal (as `derl run`'s)."""
DIAGNOSTICS = (
    "policy_loss",
    "value_loss",
    "entropy",
    "approx_kl",
    "clip_fraction",
    "explained_variance",
    "learning_rate",
)
"""The columns of `curve.csv` after the return (`derl.rl.ppo.Diagnostics`), then steps/s."""


def register(commands: argparse._SubParsersAction) -> None:
    from derl.envs import TASKS

    train = commands.add_parser(
        "train",
        help="train a controller for one body with PPO",
        description="Train a controller from scratch (--genome, --out), or go on with a stopped "
        "training (--resume DIR, with the settings it was started with).",
    )
    train.add_argument("--genome", type=Path, help="genome JSON file")
    train.add_argument("--task", choices=sorted(TASKS), help="(default ft)")
    train.add_argument("--steps", type=int, help="env steps (default 1,000,000; paper: 5M)")
    train.add_argument("--seed", type=int, help="training seed (default the paper's, 1409)")
    train.add_argument("--envs", type=at_least_one, help="env copies (default 32, the paper's)")
    train.add_argument("--threads", type=at_least_one, default=1, help="simulation threads")
    train.add_argument("--out", type=Path, help="output directory")
    train.add_argument(
        "--resume", type=Path, metavar="DIR", help="go on with the stopped training in DIR"
    )
    train.add_argument(
        "--checkpoint-every",
        type=int,
        default=CHECKPOINT_EVERY,
        metavar="N",
        help=f"save what resuming needs every N iterations (default {CHECKPOINT_EVERY}; 0: "
        "only when stopped)",
    )
    train.add_argument(
        "--tensorboard",
        type=Path,
        metavar="LOGDIR",
        help="also write each iteration's return and PPO diagnostics to TensorBoard in "
        "LOGDIR/<out folder name> (pip install 'derl[tensorboard]')",
    )
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


class _Job:
    """What one `derl train` trains and where it writes: a new training's, from its flags, or
    a stopped one's, from its folder."""

    def __init__(self, args: argparse.Namespace) -> None:
        from derl.nodes.cli.unimal import load_genome

        if args.checkpoint_every < 0:
            fail(f"--checkpoint-every: must be 0 or more, not {args.checkpoint_every}", 2)
        self.resume: bytes | None = None
        if args.resume is None:
            missing = [flag for flag in ("genome", "out") if getattr(args, flag) is None]
            if missing:
                fail(f"--{' and --'.join(missing)} required (or --resume DIR)", 2)
            self.out: Path = args.out
            self.task = args.task or DEFAULTS["task"]
            self.config = _config(self.task, args)
            _writable(self.out)
            self.genome = load_genome(args.genome)
            return
        flags = (*DEFAULTS, "genome", "out")
        given = [f"--{flag}" for flag in flags if getattr(args, flag) is not None]
        if given:
            fail(f"--resume takes the training's settings from its folder: drop {given[0]}", 2)
        self.out = args.resume
        self.task, self.config, self.genome, self.resume = _stopped(self.out)


def _config(task: str, args: argparse.Namespace):  # -> PPOConfig
    """The PPO settings of a new training's flags, or exit saying which one is wrong."""
    from pydantic import ValidationError

    from derl.lifetime import ppo_config
    from derl.rl.config import PPOHyperparameters

    steps = DEFAULTS["steps"] if args.steps is None else args.steps
    envs = args.envs or DEFAULTS["envs"]
    rollout = envs * PPOHyperparameters().rollout_steps
    if steps < rollout:  # PPO updates after whole rollouts, as the released code does
        fail(f"--steps: {steps:,} is less than one rollout, {rollout:,} env steps ({envs} "
             f"copies x {rollout // envs} steps)", 2)  # fmt: skip
    seed = DEFAULTS["seed"] if args.seed is None else args.seed
    try:
        return ppo_config(task, steps, seed, num_envs=envs)
    except ValidationError as error:
        fail(f"cannot train with these settings: {problems(error, FLAGS)}", 2)


def _writable(out: Path) -> None:
    """Exit, before any work, unless `out` can be (or is) the folder of a new training."""
    if (out / STATE).exists():
        fail(f"{out} holds a stopped training: go on with `derl train --resume {out}`, or "
             "choose another --out")  # fmt: skip
    output_directory(out)


def _stopped(folder: Path) -> tuple[str, Any, Any, bytes]:  # task, PPOConfig, Genome, state
    """The task, settings, body and state of the stopped training in `folder`, or exit saying
    why there is none."""
    from derl.rl.config import PPOConfig
    from derl.unimal import Genome

    if not (folder / STATE).is_file():
        finished = (folder / RESULT).is_file()
        why = "its training finished" if finished else "no stopped training there"
        fail(f"--resume {folder}: no {STATE} ({why})")
    try:
        saved = json.loads((folder / RESULT).read_text())
        config = PPOConfig.model_validate(saved["config"])
        genome = Genome.model_validate_json((folder / GENOME).read_text())
        return saved["task"], config, genome, (folder / STATE).read_bytes()
    except (OSError, ValueError, KeyError) as error:  # ValidationError is a ValueError
        fail(f"--resume {folder}: cannot read the training it holds: {error}")


def _train(args: argparse.Namespace) -> int:
    from derl.lifetime import learn

    job = _Job(args)
    board = _Board(args.tensorboard, job.out) if args.tensorboard else None
    config, out = job.config, job.out
    trained = config.iterations * config.batch_size
    if job.resume is None:
        if trained != config.total_steps:
            console.print(
                f"training {trained:,} env steps: --steps {config.total_steps} rounded down to "
                f"whole rollouts ({config.iterations} of {config.batch_size:,} = "
                f"{config.num_envs} copies x {config.rollout_steps} steps)",
                highlight=False,
                soft_wrap=True,
            )
        (out / GENOME).write_text(job.genome.model_dump_json(indent=2) + "\n")
    stop = threading.Event()
    _on_signals(stop)
    columns = (
        TextColumn("{task.completed:,.0f}/{task.total:,.0f} steps"),
        TextColumn("return {task.fields[ret]}"),
        TextColumn("{task.fields[sps]:,.0f} steps/s"),
    )

    def line(state: dict[str, Any]) -> str:
        share = 100 * state["completed"] / state["total"]
        return (f"{state['description']}: {state['completed']:,}/{state['total']:,} env steps "
                f"({share:.0f}%), return {state['ret']}, {state['sps']:,.0f} steps/s")  # fmt: skip

    with Shown(console, job.task, trained, columns, line, ret="-", sps=0) as shown:

        def show(progress) -> None:  # derl.rl.Progress
            ret = "-" if progress.recent_return is None else f"{progress.recent_return:.1f}"
            shown.update(completed=progress.env_steps, ret=ret, sps=progress.steps_per_second)
            if board is not None:
                board.add(progress)

        def save(summary, result, state: bytes) -> None:  # LifetimeResult, TrainResult
            _write(out, config, summary, result)
            _replace(out / STATE, state)

        try:
            summary, result = learn(
                job.genome, job.task, config, show, nthread=args.threads,
                save=save, every=args.checkpoint_every, stop=stop, resume=job.resume,
            )  # fmt: skip
        except KeyboardInterrupt:
            fail(f"stopped at once: `derl train --resume {out}` goes on from the last state "
                 "saved, if any", STOPPED)  # fmt: skip
        except ValueError as error:  # a state of another derl or configuration
            if job.resume is None:
                raise
            fail(f"--resume {out}: {error}")
        finally:
            if board is not None:
                board.close()
    if result.iterations < config.iterations:
        console.print(
            f"stopped after iteration {result.iterations} of {config.iterations} "
            f"({result.env_steps:,} env steps): checkpoint, curve and result in {out}; "
            f"`derl train --resume {out}` goes on"
        )
        return STOPPED
    _write(out, config, summary, result)
    (out / STATE).unlink(missing_ok=True)  # finished: nothing to resume
    console.print(
        f"fitness {summary.fitness:.1f} ({summary.fitness_episodes} episodes), "
        f"cost of work {summary.cost_of_work:.3g}, {summary.steps_per_second:,.0f} steps/s, "
        f"{summary.wall_time_s:.0f} s -> {out}"
    )
    return 0


def _on_signals(stop: threading.Event) -> None:
    """SIGINT and SIGTERM set `stop` (the training saves and stops at the end of an iteration);
    a second one stops at once (`KeyboardInterrupt`)."""

    def handle(number: int, _frame: object) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        name = signal.Signals(number).name
        console.print(f"{name}: saving at the end of this iteration, then stopping "
                      "(again: stop at once)", highlight=False)  # fmt: skip

    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, handle)


def _replace(path: Path, data: bytes) -> None:
    """Write `path` whole or not at all (a training killed while saving keeps the last)."""
    part = path.with_name(path.name + ".part")
    part.write_bytes(data)
    part.replace(path)


def _write(out: Path, config, summary, result) -> None:  # PPOConfig, LifetimeResult, TrainResult
    """The policy, the result so far and the curve."""
    _replace(out / CHECKPOINT, result.checkpoint.to_bytes())
    done = {"iterations": result.iterations, "finished": result.iterations == config.iterations}
    record = {"config": config.model_dump(), **summary.model_dump(), **done}
    _replace(out / RESULT, (json.dumps(record, indent=2) + "\n").encode())
    _write_curve(out, result.progress, summary.task)


def _write_curve(out: Path, progress: list, task: str) -> None:  # derl.rl.Progress
    """`curve.csv`, a row per iteration (its return blank before two episodes finished), and
    `curve.png`, the return over env steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with (out / CURVE_CSV).open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["iteration", "env_steps", "mean_return", *DIAGNOSTICS, "steps_per_s"])
        for point in progress:
            ret = "" if point.recent_return is None else point.recent_return
            diagnostics = [getattr(point.diagnostics, name) for name in DIAGNOSTICS]
            writer.writerow(
                [point.iteration, point.env_steps, ret, *diagnostics, point.steps_per_second]
            )
    shown = [(p.env_steps, p.recent_return) for p in progress if p.recent_return is not None]
    figure, axis = plt.subplots(figsize=(6, 3.5))
    if shown:
        axis.plot(*zip(*shown, strict=True))
    axis.set(xlabel="environment steps", ylabel="mean episode return (fitness term)", title=task)
    axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(out / CURVE_PNG, dpi=120)
    plt.close(figure)


class _Board:
    """Each iteration's return and diagnostics as TensorBoard scalars in LOGDIR/<out folder
    name>, at its env steps (tags named as Stable-Baselines3 names its: rollout/, train/,
    time/); a resumed training goes on after the last step written there."""

    TAGS: ClassVar[dict[str, str]] = {
        "rollout/fitness_term_mean": "recent_return",
        "time/steps_per_s": "steps_per_second",
    }

    def __init__(self, logdir: Path, out: Path) -> None:
        from derl.nodes.tools.tensorboard import NoTensorBoard, Scalars, last_steps, summary_writer

        try:
            writer = summary_writer()
        except NoTensorBoard as error:
            fail(f"--tensorboard: {error}")
        folder = logdir / out.resolve().name
        self.scalars = Scalars(writer(str(folder)), last_steps(folder))

    def add(self, progress) -> None:  # derl.rl.Progress
        import time

        now = time.time()
        values = {tag: getattr(progress, name) for tag, name in self.TAGS.items()}
        if progress.diagnostics is not None:
            values.update({f"train/{name}": getattr(progress.diagnostics, name)
                           for name in DIAGNOSTICS})  # fmt: skip
        for tag, value in values.items():
            if value is not None and math.isfinite(value):
                self.scalars.scalar(tag, value, progress.env_steps, now)

    def close(self) -> None:
        self.scalars.writer.close()


def _rollout(args: argparse.Namespace) -> int:
    from derl.envs.video import VideoError, check_video_path, write_video
    from derl.replay import NotTrained, Trained, play

    try:
        trained = Trained.load(args.dir)
    except NotTrained as error:
        fail(str(error), code=2)
    if args.video:
        try:  # before the episode is filmed, not after
            check_video_path(args.video)
        except VideoError as error:
            fail(f"--video {error}", error.code)
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
