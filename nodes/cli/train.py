"""`derl train` and `derl rollout`: learn a controller for one body, and replay what was learnt.

Parsing and printing only: the training's work (its folder, saves, resume, extension, signals,
each iteration's record to the curve and TensorBoard) is `derl.training`'s, the folder's layout
`derl.agent_folder`'s, the replay `derl.replay`'s.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

from rich.progress import TextColumn

from derl.nodes.cli.options import (
    Setting,
    at_least_one,
    fail,
    fail_invalid,
    output_directory,
    setting,
    task_name,
)
from derl.nodes.cli.progress import Shown, output_console
from derl.nodes.errors import USAGE
from derl.replay import EPISODE_STEPS
from derl.validation import problems

if TYPE_CHECKING:
    from derl.metrics import Record

console = output_console()

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


def register(commands: argparse._SubParsersAction) -> None:
    train = commands.add_parser(
        "train",
        help="train a controller for one body with PPO",
        description="Train a controller from scratch (--genome, --out), go on with a stopped "
        "training (--resume DIR, with the settings it was started with), or extend a finished "
        "one (--resume DIR --steps N, a larger budget).",
    )
    train.add_argument("--genome", type=Path, help="genome JSON file")
    train.add_argument(
        "--task",
        type=task_name,
        help="ft, vt, mvt, a test task, or an installed plugin's task (default ft)",
    )
    train.add_argument(
        "--steps",
        type=int,
        help="env steps (default 1,000,000; paper: 5M); with --resume, the larger budget an "
        "extension trains to",
    )
    train.add_argument("--seed", type=int, help="training seed (default the paper's, 1409)")
    train.add_argument("--envs", type=at_least_one, help="env copies (default 32, the paper's)")
    train.add_argument("--threads", type=at_least_one, default=1, help="simulation threads")
    train.add_argument("--out", type=Path, help="output directory")
    train.add_argument(
        "--settings",
        type=Path,
        metavar="FILE.yaml",
        help="PPO hyperparameters of a new training, as a profile's: a YAML file with a ppo "
        "mapping (docs/configuration.md)",
    )
    train.add_argument(
        "--set",
        action="append",
        type=setting,
        default=[],
        metavar="ppo.KEY=VALUE",
        help="change a PPO hyperparameter of a new training, e.g. --set ppo.lr=1e-4 "
        "(repeatable; after --settings)",
    )
    train.add_argument(
        "--resume",
        type=Path,
        metavar="DIR",
        help="go on with the stopped training in DIR, or extend a finished one (--steps)",
    )
    train.add_argument(
        "--checkpoint-every",
        type=int,
        default=CHECKPOINT_EVERY,
        metavar="N",
        help=f"save what resuming needs every N iterations (default {CHECKPOINT_EVERY}; 0: "
        "only when stopped and at the end)",
    )
    train.add_argument(
        "--tensorboard",
        type=Path,
        metavar="LOGDIR",
        help="also write each iteration's return and PPO diagnostics to TensorBoard in "
        "LOGDIR/<out folder name> (pip install 'derl[tensorboard]'); a resume writes where "
        "its training wrote, unless given another",
    )
    train.set_defaults(handler=_train)

    rollout = commands.add_parser(
        "rollout",
        help="replay a trained policy deterministically",
        description="Replay the trained body of DIR: the output folder of `derl train`, or a "
        "run's best/NN-agent folder (the body is replayed in the task it was trained in).",
    )
    rollout.add_argument("dir", type=Path, help="a trained agent's folder")
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
    from derl.training import (
        Finished,
        NoBoard,
        NothingToResume,
        Stop,
        Taken,
        TrainingError,
        open_board,
        run,
    )

    stop = Stop(lambda line: console.print(line, highlight=False))
    stop.install()  # before the slow imports: a Ctrl-C there is no traceback
    if args.checkpoint_every < 0:
        fail(f"--checkpoint-every: must be 0 or more, not {args.checkpoint_every}", USAGE)
    out = args.out
    try:
        plan = _plan(args)
    except Taken as error:
        how = {"a finished training": f"extend it with `derl train --resume {out} --steps N`",
               "a stopped training": f"go on with `derl train --resume {out}`"}  # fmt: skip
        fail(f"{error}: {how[error.held] + ', or ' if error.held in how else ''}choose "
             "another --out", USAGE)  # fmt: skip
    except Finished as error:
        fail(f"--resume {args.resume}: {error}: extend it with a larger --steps")
    except NothingToResume as error:
        fail(f"--resume {args.resume}: {error}")
    if stop.event.is_set():
        fail("stopped before the training began: nothing written", STOPPED)
    config, out = plan.config, plan.folder.path
    fresh = not out.exists()
    output_directory(out)
    try:
        board = open_board(plan)
    except NoBoard as error:
        if fresh:
            out.rmdir()
        fail(f"--tensorboard {plan.settings.tensorboard}: {error}", USAGE)
    trained = config.iterations * config.batch_size
    if plan.state is None and trained != config.total_steps:
        console.print(
            f"training {trained:,} env steps: --steps {config.total_steps} rounded down to "
            f"whole rollouts ({config.iterations} of {config.batch_size:,} = "
            f"{config.num_envs} copies x {config.rollout_steps} steps)",
            highlight=False,
            soft_wrap=True,
        )
    columns = (
        TextColumn("{task.completed:,.0f}/{task.total:,.0f} steps"),
        TextColumn("return {task.fields[ret]}"),
        TextColumn("{task.fields[sps]:,.0f} steps/s"),
    )

    def line(state: dict[str, Any]) -> str:
        share = 100 * state["completed"] / state["total"]
        return (f"{state['description']}: {state['completed']:,}/{state['total']:,} env steps "
                f"({share:.0f}%), return {state['ret']}, {state['sps']:,.0f} steps/s")  # fmt: skip

    with Shown(console, plan.settings.task, trained, columns, line, ret="-", sps=0) as shown:

        def show(values: Record) -> None:
            ret = values["mean_return"]
            shown.update(completed=values["env_steps"], sps=values["steps_per_s"],
                         ret="-" if ret is None else f"{ret:.1f}")  # fmt: skip

        try:
            done = run(plan, show, stop, board, args.checkpoint_every, args.threads)
        except KeyboardInterrupt:
            fail(f"stopped at once: `derl train --resume {out}` goes on from the last state "
                 "saved (from the beginning if none was)", STOPPED)  # fmt: skip
        except TrainingError as error:
            fail(f"--resume {out}: {error}")
        finally:
            if board is not None:
                board.close()
    summary, result = done.summary, done.result
    if not done.finished:
        console.print(
            f"stopped after iteration {result.iterations} of {config.iterations} "
            f"({result.env_steps:,} env steps): checkpoint, curve and result in {out}; "
            f"`derl train --resume {out}` goes on"
        )
        return STOPPED
    console.print(
        f"fitness {summary.fitness:.1f} ({summary.fitness_episodes} episodes), "
        f"cost of work {summary.cost_of_work:.3g}, {summary.steps_per_second:,.0f} steps/s, "
        f"{summary.wall_time_s:.0f} s -> {out}"
    )
    return 0


def _plan(args: argparse.Namespace):  # -> derl.training.Plan
    """What this `derl train` trains: a new training's flags, or a stopped or finished one's
    folder (with a larger --steps: extended)."""
    from derl.training import begin, resume

    if args.resume is None:
        missing = [flag for flag in ("genome", "out") if getattr(args, flag) is None]
        if missing:
            fail(f"--{' and --'.join(missing)} required (or --resume DIR)", USAGE)
        from derl.nodes.cli.unimal import load_genome

        task = args.task or DEFAULTS["task"]
        config = _config(task, args)
        if args.out.exists() and not args.out.is_dir():
            fail(f"--out {args.out} is a file, not a directory")
        return begin(load_genome(args.genome), task, config, args.out, args.tensorboard)
    flags = ("task", "seed", "envs", "genome", "out", "settings")
    given = [f"--{flag}" for flag in flags if getattr(args, flag) is not None]
    given += ["--set"] * bool(args.set)
    if given:
        fail(f"--resume takes the training's settings from its folder: drop {given[0]} (--steps "
             "extends it)", USAGE)  # fmt: skip
    if not args.resume.is_dir():
        fail(f"--resume {args.resume}: no such directory", USAGE)
    return resume(args.resume, args.steps, args.tensorboard)


def _config(task: str, args: argparse.Namespace):  # -> PPOConfig
    """The PPO settings of a new training's flags and --set changes, or exit saying which one is
    wrong."""
    from pydantic import ValidationError

    from derl.lifetime import ppo_config
    from derl.rl.config import PPOHyperparameters

    changes = _changes(args.settings, args.set)
    steps = DEFAULTS["steps"] if args.steps is None else args.steps
    envs = args.envs or DEFAULTS["envs"]
    rollout_steps = changes.get("rollout_steps", PPOHyperparameters().rollout_steps)
    rollout = envs * rollout_steps if isinstance(rollout_steps, int) else 0
    if steps < rollout:  # PPO updates after whole rollouts, as the released code does
        fail(f"--steps: {steps:,} is less than one rollout, {rollout:,} env steps ({envs} "
             f"copies x {rollout // envs} steps)", USAGE)  # fmt: skip
    seed = DEFAULTS["seed"] if args.seed is None else args.seed
    try:
        return ppo_config(task, steps, seed, num_envs=envs, **changes)
    except ValidationError as error:
        fail(f"cannot train with these settings: {problems(error, FLAGS)}", USAGE)


def _changes(path: Path | None, settings: list[Setting]) -> dict[str, Any]:
    """The PPO hyperparameters --settings FILE.yaml and --set ppo.KEY=VALUE change, or exit
    saying which one is wrong."""
    import yaml
    from pydantic import ValidationError

    from derl.evolution.config import set_dotted
    from derl.training import TrainingChanges

    data: Any = {}
    if path is not None:
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except FileNotFoundError:
            fail(f"--settings {path}: no such file", USAGE)
        except (OSError, yaml.YAMLError) as error:
            fail(f"--settings {path}: cannot read it: {' '.join(str(error).split())}")
        if not isinstance(data, dict):
            fail(f"--settings {path}: give a mapping, e.g. `ppo: {{lr: 1.0e-4}}`")
    what = " and ".join([f"--settings {path}"] * (path is not None) +
                        [f"--set {change.text}" for change in settings])  # fmt: skip
    try:
        for change in settings:
            set_dotted(data, change.key, change.value)
        chosen = TrainingChanges.model_validate(data)
    except ValueError as error:  # ValidationError is one
        if isinstance(error, ValidationError):
            fail_invalid(what, error, TrainingChanges, code=USAGE)
        fail(f"{what}: {error}", USAGE)
    return chosen.ppo.model_dump(exclude_unset=True)


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
