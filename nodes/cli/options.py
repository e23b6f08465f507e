"""Flags shared by the commands (how a node joins the bus, which profile a run uses), and the one
way a command reports bad input (`fail`: a `DerlError`, printed by `main` in one line)."""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import shlex
import socket
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple, NoReturn, TypeGuard, get_args

import yaml
import zenoh
from pydantic import BaseModel, ValidationError

from derl.evolution.config import NoProfile, setting_keys
from derl.nodes.errors import FAILED, IN_USE, USAGE, DerlError
from derl.nodes.runtime.bus import ZenohOptions
from derl.validation import problems

PROFILE_KEY = "profile"  # in a profile file: the built-in profile it starts from
SUFFIX_CHARS = 64  # of a default directory name, for its --set changes
DEFAULT_PORT = 7447  # Zenoh's own default: the local run's port unless $DERL_LOCAL_PORT says
PORT_ENV = "DERL_LOCAL_PORT"
PROBE_S = 0.5  # how long to try a TCP connection to tell whether something listens


def fail(message: str, code: int = 1) -> NoReturn:
    """End the command: `derl: message` on stderr (one line) and exit status `code` (`main`)."""
    raise DerlError(message, code)


def task_name(text: str) -> str:
    """An argparse type: a task's name (a built-in's, an installed plugin's, or
    ``package.module:name``), as a profile keeps it."""
    from derl.envs.registry import TASK_REGISTRY
    from derl.plugins import PluginError, canonical

    try:
        TASK_REGISTRY.get(text)
    except PluginError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return canonical(text)


def at_least_one(text: str) -> int:
    """An argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
"""Zenoh's link protocols whose address is HOST:PORT (the others, e.g. unixsock-stream, a path)."""


def endpoint(text: str) -> str:
    """An argparse type: a Zenoh endpoint, PROTOCOL/ADDRESS; HOST:PORT (a port 0-65535) for
    the IP protocols, optionally followed by Zenoh's ?config or #metadata."""
    protocol, slash, address = text.partition("/")
    if not slash or not protocol or not address:
        raise argparse.ArgumentTypeError(f"{text!r} is not an endpoint: give e.g. tcp/HOST:7447")
    if protocol not in IP_PROTOCOLS:
        return text
    match = re.fullmatch(r"(\[[^\]]+\]|[^:\[\]?#]+):(\d+)([?#].*)?", address)
    if match is None:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not an endpoint: give {protocol}/HOST:PORT, e.g. {protocol}/10.0.0.5:7447"
        )
    if int(match[2]) > 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: {match[2]} is not a port number (0-65535)")
    return text


def add_bus_arguments(parser: argparse.ArgumentParser, run_required: bool = True) -> None:
    group = parser.add_argument_group("bus")
    group.add_argument("--run", required=run_required, help="run id (keys live under derl/<run>/)")
    for flag, example in (("--listen", "tcp/0.0.0.0:7447"), ("--connect", "tcp/10.0.0.5:7447")):
        group.add_argument(
            flag,
            action="append",
            type=endpoint,
            default=[],
            metavar="EP",
            help=f"endpoint to {flag[2:]} {'to' if flag == '--connect' else 'on'}, "
            f"e.g. {example} (repeatable)",
        )
    group.add_argument("--mode", choices=["peer", "client"], default="peer")
    group.add_argument("--zenoh-config", type=Path, help="Zenoh JSON5 config (TLS, ACL, ...)")
    group.add_argument("--multicast", action="store_true", help="turn multicast scouting on")


def port_number(text: str) -> int:
    """An argparse type: a TCP port, 0 to 65535."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is not a port number (0-65535)")
    return port


def add_port_argument(parser: argparse.ArgumentParser, what: str) -> None:
    """`--port`: where this host's coordinator listens on 127.0.0.1, by default the local run's
    port, where the watching tools connect when given no endpoint."""

    def port(text: str) -> int:  # a default from $DERL_LOCAL_PORT is checked like the flag
        try:
            return port_number(text)
        except argparse.ArgumentTypeError as error:
            if text == os.environ.get(PORT_ENV):
                raise argparse.ArgumentTypeError(f"{error} (${PORT_ENV})") from None
            raise

    parser.add_argument(
        "--port",
        type=port,
        default=default_port(),
        help=f"{what} (default ${PORT_ENV}, else {DEFAULT_PORT}: where `derl monitor`, "
        "`topic` ... connect when given no endpoint; 0: a free one)",
    )


def default_port() -> str:
    """`--port`'s default: $DERL_LOCAL_PORT, else `DEFAULT_PORT`."""
    return os.environ.get(PORT_ENV) or str(DEFAULT_PORT)


def local_endpoint() -> str:
    """The local run's endpoint: 127.0.0.1 at $DERL_LOCAL_PORT, else 7447 (`derl run`'s)."""
    text = default_port()
    try:
        port = port_number(text)
    except argparse.ArgumentTypeError as error:
        fail(f"{PORT_ENV}={text}: {error}")
    return f"tcp/127.0.0.1:{port}"


def watch_options(args: argparse.Namespace) -> ZenohOptions:
    """How a watching tool joins the bus: as its flags say, else connected to the local run's
    endpoint (`local_endpoint`), where `derl run` listens."""
    options = options_from(args)
    if options.listen or options.connect or options.config_file:
        return options
    return options.model_copy(update={"connect": (local_endpoint(),)})


def publish_options(args: argparse.Namespace) -> ZenohOptions:
    """How a tool that publishes a run (`derl replay`) joins the bus: as its flags say, else on
    the local run's endpoint, connected to it when something listens there (a live run), else
    listening on it, so that watchers given no endpoint hear it."""
    options = watch_options(args)
    local = local_endpoint()
    if options.connect != (local,) or listening(local) or options.mode != "peer":
        return options
    return options.model_copy(update={"connect": (), "listen": (local,)})


def listening(endpoint: str) -> bool | None:
    """Whether something accepts TCP connections at a ``tcp/HOST:PORT`` endpoint (None: not such
    an endpoint)."""
    match = re.fullmatch(r"tcp/\[?([^\]/]+?)\]?:(\d+)", endpoint)
    if match is None:
        return None
    try:
        with socket.create_connection((match[1], int(match[2])), timeout=PROBE_S):
            return True
    except OSError:
        return False


def how_joined(options: ZenohOptions) -> str:
    """How a tool joined the bus, in words, for a message saying it heard nothing: its mode,
    the endpoints it connected to (those where nothing listens marked) or listened on."""
    parts: list[str] = [options.mode]
    for endpoint in options.connect:
        quiet = listening(endpoint) is False
        parts.append(f"connected to {endpoint}{', where nothing listens' if quiet else ''}")
    parts += [f"listening on {endpoint}" for endpoint in options.listen]
    if options.config_file:
        parts.append(f"config {options.config_file}")
    return ", ".join(parts)


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
    add_set_argument(parser)
    parser.add_argument(
        "--env", help="world: ft, vt, mvt or a plugin's task (overrides the profile)"
    )
    parser.add_argument(
        "--seed",
        type=int,
        help="the run's evolution seed: initial bodies and tournaments (overrides the profile; "
        "replicates of one profile differ by it)",
    )


def add_set_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--set",
        action="append",
        type=setting,
        default=[],
        metavar="KEY=VALUE",
        help="change one setting of the profile, e.g. --set ppo.lr=1e-4 --set total=200: a "
        "dotted key, a YAML value, checked like the profile file (repeatable)",
    )


class Setting(NamedTuple):
    """One ``--set KEY=VALUE``: the dotted key, the value read as YAML, and the text given."""

    key: str
    value: object
    text: str


def setting(text: str) -> Setting:
    """An argparse type: ``KEY=VALUE``, the value read as YAML."""
    key, equals, value = text.partition("=")
    key = key.strip()
    if not equals or not key:
        raise argparse.ArgumentTypeError(f"{text!r} is not KEY=VALUE (e.g. ppo.lr=1e-4)")
    if key == PROFILE_KEY:
        raise argparse.ArgumentTypeError("the profile is chosen with --profile")
    try:
        return Setting(key, yaml.safe_load(value), text)
    except yaml.YAMLError as error:
        raise argparse.ArgumentTypeError(
            f"{text}: the value is not YAML ({getattr(error, 'problem', error)})"
        ) from None


def set_arguments(changes: list[Setting]) -> list[str]:
    """The command-line arguments that make `changes` again (a node's, or to resume)."""
    return [part for change in changes for part in ("--set", change.text)]


def set_suffix(changes: list[Setting]) -> str:
    """What a default directory name adds for `changes` (`-total=200-ppo.lr=1e-4`), so a run
    with other settings does not resume one without them; a hash where it would be long."""
    if not changes:
        return ""
    text = re.sub(r"[^A-Za-z0-9_.=+-]", "_", "-".join(change.text for change in changes))
    if len(text) > SUFFIX_CHARS:
        text = text[: SUFFIX_CHARS - 9] + "-" + hashlib.sha1(text.encode()).hexdigest()[:8]
    return f"-{text}"


def _described(args: argparse.Namespace, kind: str) -> str:
    """What a profile error names: the profile and the --set changes made to it."""
    changes = shlex.join(set_arguments(args.set))
    return f"{kind} {args.profile}" + (f" with {changes}" if changes else "")


def profile_from(args: argparse.Namespace):  # -> EvolutionConfig
    """The run's profile from --profile/--set/--env/--seed, or exit with the reason it is not
    valid; the plugins it names are tried first (`derl.extensions.check_profile_plugins`), so a
    plugin that cannot work stops the command before any node starts."""
    from derl.evolution import EvolutionConfig, load_profile
    from derl.extensions import check_profile_plugins

    def load(changes: list[tuple[str, object]]) -> EvolutionConfig:
        config = load_profile(args.profile, changes, world=args.env, seed=args.seed)
        check_profile_plugins(config)
        return config

    return _profile_or_exit(_described(args, "profile"), EvolutionConfig, load, args.set)


def study_profile_from(args: argparse.Namespace):  # -> StudyConfig
    """The study's profile from --profile/--set, or exit with the reason it is not valid."""
    from derl.analysis.study import StudyConfig, load_study_profile

    return _profile_or_exit(
        _described(args, "study profile"),
        StudyConfig,
        lambda changes: load_study_profile(args.profile, changes),
        args.set,
    )


def _profile_or_exit(
    what: str,
    model: type[BaseModel],
    load: Callable[[list[tuple[str, object]]], BaseModel],
    changes: list[Setting],
):
    """`load(changes)`, or exit with one line saying why `what` is not a valid `model`: a usage
    error (exit status 2) where the profile named does not exist or `changes` (--set) are at
    fault: a setting of theirs is wrong, or the profile is valid without them (a rule between
    settings, e.g. in_flight < population, that a change breaks)."""
    pairs = [(change.key, change.value) for change in changes]
    try:
        return load(pairs)
    except ValidationError as error:
        keys = [change.key for change in changes]
        at = [".".join(map(str, e["loc"])) for e in error.errors()]
        ours = any(loc == key or loc.startswith(f"{key}.") for loc in at for key in keys)
        fail_invalid(what, error, model, top=(PROFILE_KEY,),
                     code=USAGE if ours or (changes and _valid(load)) else FAILED)  # fmt: skip
    except NoProfile as error:
        fail(f"{what}: {error}", USAGE)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        fail(f"{what}: not valid YAML{where}: {getattr(error, 'problem', error)}")
    except (ValueError, OSError) as error:
        fail(f"{what}: {error}")


def _valid(load: Callable[[list[tuple[str, object]]], BaseModel]) -> bool:
    """Whether `load` gives a valid profile with no changes."""
    try:
        load([])
    except (ValidationError, ValueError, OSError, yaml.YAMLError):
        return False
    return True


def fail_invalid(
    what: str,
    error: ValidationError,
    model: type[BaseModel],
    top: tuple[str, ...] = (),
    code: int = 1,
) -> NoReturn:
    """Exit (status `code`) saying why a file does not fit `model`: its first unknown key with
    the keys valid there (at the top, also `top`), else every problem, in one line."""
    unknown = [e["loc"] for e in error.errors() if e["type"] == "extra_forbidden"]
    if unknown:
        key = unknown[0]
        valid = [*valid_keys(model, key[:-1]), *(top if len(key) == 1 else ())]
        fail(f"{what}: unknown key {'.'.join(map(str, key))!r}; valid keys: {', '.join(valid)}",
             code)  # fmt: skip
    fail(f"{what}: {problems(error)}", code)


def valid_keys(model: type[BaseModel], path: tuple[object, ...]) -> list[str]:
    """The keys valid at `path` (an error's location: fields, list indices, union tags) inside
    `model`; none where `path` does not lead to a model."""
    inner: object = model
    for part in path:
        inner = _inside(inner, part)
    return setting_keys(inner) if _is_model(inner) else []


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
    return output_directory(path, "run directory")


def output_directory(path: Path, what: str = "--out") -> Path:
    """`path` as a folder to write in (created if missing), or exit, before any work, saying why
    it cannot be one (`what`: how the message names it)."""
    if path.exists() and not path.is_dir():
        fail(f"{what} {path} is a file, not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        fail(f"cannot make {what} {path}: {error.strerror}")
    if not os.access(path, os.W_OK | os.X_OK):
        fail(f"cannot write in {what} {path}: permission denied")
    return path


def output_file(path: Path, what: str) -> Path:
    """`path` as a file to write (its folder created if missing), or exit, before any work, saying
    why it cannot be one (`what`: how the message names it); tried, as the permissions do not say
    it for root, nor on /proc or a read-only file system."""
    if path.is_dir():
        fail(f"{what} {path} is a directory, not a file")
    output_directory(path.parent, what)
    existed = path.exists()
    try:
        with path.open("ab"):
            pass
    except OSError as error:
        fail(f"cannot write {what} {path}: {(error.strerror or str(error)).lower()}")
    if not existed:
        path.unlink()
    return path
