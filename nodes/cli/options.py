"""Flags shared by the commands (how a node joins the bus, which profile a run uses), and the one
way a command reports bad input (`fail`: a `DerlError`, printed by `main` in one line)."""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn, TypeGuard, get_args

import yaml
import zenoh
from derl.nodes.errors import IN_USE, DerlError
from derl.nodes.runtime.bus import ZenohOptions
from pydantic import BaseModel, ValidationError

from derl.validation import problems

PROFILE_KEY = "profile"  # in a profile file: the built-in profile it starts from


def fail(message: str, code: int = 1) -> NoReturn:
    """End the command: `derl: message` on stderr (one line) and exit status `code` (`main`)."""
    raise DerlError(message, code)


def at_least_one(text: str) -> int:
    """An argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


def add_bus_arguments(parser: argparse.ArgumentParser, run_required: bool = True) -> None:
    group = parser.add_argument_group("bus")
    group.add_argument("--run", required=run_required, help="run id (keys live under derl/<run>/)")
    for flag, example in (("--listen", "tcp/0.0.0.0:7447"), ("--connect", "tcp/10.0.0.5:7447")):
        group.add_argument(
            flag,
            action="append",
            default=[],
            metavar="EP",
            help=f"endpoint to {flag[2:]} {'to' if flag == '--connect' else 'on'}, "
            f"e.g. {example} (repeatable)",
        )
    group.add_argument("--mode", choices=["peer", "client"], default="peer")
    group.add_argument("--zenoh-config", type=Path, help="Zenoh JSON5 config (TLS, ACL, ...)")
    group.add_argument("--multicast", action="store_true", help="turn multicast scouting on")


def options_from(args: argparse.Namespace, mode: str | None = None) -> ZenohOptions:
    return ZenohOptions(
        mode=mode or args.mode,
        listen=tuple(args.listen),
        connect=tuple(args.connect),
        multicast=args.multicast,
        config_file=args.zenoh_config,
    )


def fail_on_bus(error: zenoh.ZError) -> NoReturn:
    """Exit with Zenoh's reason in one line: a port in use with `IN_USE`, anything else with 1."""
    text = str(error)
    if "Address already in use" in text:
        where = re.search(r"bound to (\S+?):? \[", text)
        endpoint = where[1] if where else "its endpoint"
        fail(f"cannot listen on {endpoint}: the port is in use (another node, router or run?)",
             IN_USE)  # fmt: skip
    fail("bus: " + re.sub(r" at /[^ \]]+", "", text))  # without Zenoh's source locations


def add_profile_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", default="smoke", help="smoke | demo | paper | FILE.yaml")
    parser.add_argument("--env", choices=["ft", "vt", "mvt"], help="world (overrides the profile)")
    parser.add_argument(
        "--seed",
        type=int,
        help="the run's evolution seed: initial bodies and tournaments (overrides the profile; "
        "replicates of one profile differ by it)",
    )


def profile_from(args: argparse.Namespace):  # -> EvolutionConfig
    """The run's profile from --profile/--env, or exit with the reason it is not valid."""
    from derl.evolution import EvolutionConfig, load_profile

    return _profile_or_exit(
        f"profile {args.profile}",
        EvolutionConfig,
        lambda: load_profile(args.profile, world=args.env, seed=args.seed),
    )


def study_profile_from(args: argparse.Namespace):  # -> StudyConfig
    """The study's profile from --profile, or exit with the reason it is not valid."""
    from derl.analysis.study import StudyConfig, load_study_profile

    return _profile_or_exit(
        f"study profile {args.profile}", StudyConfig, lambda: load_study_profile(args.profile)
    )


def _profile_or_exit(what: str, model: type[BaseModel], load: Callable[[], BaseModel]):
    """`load()`, or exit with one line saying why `what` is not a valid `model`."""
    try:
        return load()
    except ValidationError as error:
        fail_invalid(what, error, model, top=(PROFILE_KEY,))
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        fail(f"{what}: not valid YAML{at}: {getattr(error, 'problem', error)}")
    except (ValueError, OSError) as error:
        fail(f"{what}: {error}")


def fail_invalid(
    what: str, error: ValidationError, model: type[BaseModel], top: tuple[str, ...] = ()
) -> NoReturn:
    """Exit saying why a file does not fit `model`: its first unknown key with the keys valid
    there (at the top, also `top`), else every problem, in one line."""
    unknown = [e["loc"] for e in error.errors() if e["type"] == "extra_forbidden"]
    if unknown:
        key = unknown[0]
        valid = [*valid_keys(model, key[:-1]), *(top if len(key) == 1 else ())]
        fail(f"{what}: unknown key {'.'.join(map(str, key))!r}; valid keys: {', '.join(valid)}")
    fail(f"{what}: {problems(error)}")


def valid_keys(model: type[BaseModel], path: tuple[object, ...]) -> list[str]:
    """The keys valid at `path` (an error's location: fields, list indices, union tags) inside
    `model`; none where `path` does not lead to a model."""
    inner: object = model
    for part in path:
        inner = _inside(inner, part)
    return list(inner.model_fields) if _is_model(inner) else []


def _inside(annotation: object, part: object) -> object:
    """The annotation at one step of an error's location inside `annotation`."""
    if _is_model(annotation):
        field = annotation.model_fields.get(str(part))
        return None if field is None else field.annotation
    args = get_args(annotation)
    if isinstance(part, int):  # an item of a list or tuple
        return args[0] if args else None
    models = [a for a in args if _is_model(a)]
    for member in models:  # a tagged union's location names the member by its tag
        if any(part in get_args(f.annotation) for f in member.model_fields.values()):
            return member
    return _inside(models[0], part) if models else None  # an optional model


def _is_model(annotation: object) -> TypeGuard[type[BaseModel]]:
    return isinstance(annotation, type) and issubclass(annotation, BaseModel)


def run_directory(path: Path) -> Path:
    """`path` as a run directory (created if missing), or exit saying why it cannot be one."""
    if path.exists() and not path.is_dir():
        fail(f"run directory {path} is a file, not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        fail(f"cannot make run directory {path}: {error.strerror}")
    return path
