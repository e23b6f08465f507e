"""`derl run`: a whole run on this host: coordinator, K trainers and an evaluator, on loopback.

The nodes are those of the local launch graph (`nodes.launch.local`: `launch/local.yaml`) with
this run's numbers. Each node is its own process (its log in RUN_DIR/logs/), connected through the
coordinator's loopback endpoint (port 7447 unless --port or $DERL_LOCAL_PORT says otherwise: a
bare `derl monitor` connects there, across restarts) with multicast off. They are supervised as
`derl launch` does (`nodes.launch.supervisor`): a trainer or evaluator that dies is started
again, and a coordinator that dies is started again alone, resumes from its journal and hears the
trainers' reports again (they re-send until acknowledged); a coordinator that refuses to start
stops the run at once. It ends when the coordinator finishes the run; meanwhile it shows bodies
born, best fitness, steps/s and time left. Ctrl-C stops every node; running it again on the same
run directory resumes the run from its journal.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import shlex
import signal
import statistics
import threading
import unicodedata
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.progress import TextColumn

from derl.messages import RunStatus
from derl.nodes.cli.options import (
    add_port_argument,
    add_profile_arguments,
    at_least_one,
    default_port,
    fail,
    local_endpoint,
    profile_from,
    run_directory,
    set_arguments,
    set_suffix,
)
from derl.nodes.cli.progress import Shown, output_console
from derl.nodes.errors import IN_USE, USAGE
from derl.nodes.journal.history import load_history
from derl.nodes.launch.commands import NodeCommand, build_commands
from derl.nodes.launch.local import local_launch
from derl.nodes.launch.supervisor import Supervisor
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.runtime.ports import bind_error, free_port
from derl.nodes.runtime.rundir import lock_run_dir

if TYPE_CHECKING:
    from derl.evolution import EvolutionConfig

console = output_console()  # no wrapping, and progress lines, in a log file

MAX_RESTARTS = 10  # of a node beside the graph's (the TensorBoard watcher)
FREE_RUNNING = (
    "in_flight 0: free-running (the released code's rule): a child is bred from the bodies born "
    "most recently, so the births depend on the order trainings finish in, and the same profile "
    "and seed do not give the same run again"
)  # said once, as a run of in_flight 0 starts


def register(commands: argparse._SubParsersAction) -> None:
    run = commands.add_parser("run", help="run evolution on this host (all nodes, supervised)")
    add_profile_arguments(run)
    run.add_argument("--workers", type=at_least_one, default=2, help="trainer processes (2)")
    run.add_argument(
        "--tensorboard",
        type=Path,
        metavar="LOGDIR",
        help="also write the run's curves to TensorBoard event files in LOGDIR/<run> "
        "(`derl tensorboard`), and each child's training, with its PPO diagnostics, in "
        "LOGDIR/<run>/children/<agent> (pip install 'derl[tensorboard]')",
    )
    run.add_argument(
        "--run-dir", type=Path, help="default: runs/<profile>-<world>[-s<seed>][-<KEY=VALUE>...]"
    )
    add_extend_argument(run)
    add_port_argument(run, "the coordinator's port on 127.0.0.1")
    run.set_defaults(handler=_run)


def add_extend_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--extend",
        action="store_true",
        help="with --set total=N and --run-dir: raise the total of the run begun there to N "
        "bodies (it goes on with the same births a run of N would have had); any other --set "
        "that differs from the run's saved settings is refused",
    )


def _run(args: argparse.Namespace) -> int:
    config = profile_from(args)
    run_dir, config = run_directory_of(args, config)
    port = listenable(args.port)
    run = local_run_id(run_dir)
    endpoint = f"tcp/127.0.0.1:{port}"
    workers = {"trainer": args.workers, "evaluator": int(config.eval_top > 0)}
    graph = local_launch(run, endpoint, workers, args.tensorboard,
                         **coordinator_settings(args, run_dir))  # fmt: skip
    nodes = build_commands(graph)  # trainers writing each training with --tensorboard
    board = ("--tensorboard", str(args.tensorboard)) if args.tensorboard else ()
    if args.tensorboard:  # and the run's curves
        nodes.append(tensorboard_node(run, endpoint, args.tensorboard))
    env = ("--env", args.env) if args.env else ()
    seed = ("--seed", str(args.seed)) if args.seed is not None else ()
    port_flag = ("--port", str(args.port)) if str(args.port) != default_port() else ()
    again = shlex.join(["derl", "run", "--profile", args.profile, *set_arguments(args.set),
                        *env, *seed, "--run-dir", str(run_dir), *port_flag, *board])  # fmt: skip
    return run_nodes(nodes, run, endpoint, config, run_dir, run_dir / "logs", f"`{again}`")


def run_directory_of(
    args: argparse.Namespace, config: EvolutionConfig
) -> tuple[Path, EvolutionConfig]:
    """The run directory of `--run-dir` or the default one of the profile (created), and the
    settings the run goes on with there (`resumed_config`); or exit saying that another
    coordinator holds it, or that it is a `derl train` folder."""
    from derl.agent_folder import AgentFolder

    replicate = "" if args.seed is None else f"-s{args.seed}"
    default = f"{config.name}-{config.world}{replicate}{set_suffix(args.set)}"
    if args.extend and args.run_dir is None:
        fail("--extend: name the run to extend with --run-dir", USAGE)
    if args.run_dir is not None and AgentFolder(args.run_dir).holds_training():
        fail(f"--run-dir {args.run_dir} holds a `derl train` output, not a run: choose another "
             "folder", USAGE)  # fmt: skip
    run_dir = run_directory(args.run_dir or Path("runs") / default)
    with lock_run_dir(run_dir):  # only to say now, not after restarts, that it is taken
        return run_dir, resumed_config(args, run_dir, config)


def resumed_config(
    args: argparse.Namespace, run_dir: Path, config: EvolutionConfig
) -> EvolutionConfig:
    """The settings of the run in `run_dir`: `config` for a new run; for one begun there, its
    saved settings (the coordinator keeps them), or exit (status 2) where a --set asks for
    another value of a setting than the saved one, unless it is `--extend`'s total, larger:
    saved now, the coordinator goes on to it."""
    from derl.nodes.coordinator.run.files import save_config, saved_config

    saved = saved_config(run_dir)
    if saved is None or (saved.name, saved.world, saved.seed) != (
        config.name, config.world, config.seed
    ):  # fmt: skip
        return config  # a new run, or one the coordinator refuses, saying why
    was, now = saved.model_dump(mode="json"), config.model_dump(mode="json")
    more = config.total > saved.total
    for change in args.set:
        old, new = _at(was, change.key), _at(now, change.key)
        if old == new or (change.key == "total" and args.extend and more):
            continue
        hint = " (--extend raises it)" if change.key == "total" and more else ""
        fail(f"--set {change.key}={json.dumps(new)}: the run in {run_dir} has {change.key} "
             f"{json.dumps(old)}{hint}; a run keeps its settings: use a new --run-dir to run "
             "with others", USAGE)  # fmt: skip
    if args.extend and more and saved.end == "released":
        fail(f"--extend: the run in {run_dir} ends as the released code did (end: released): "
             "it dropped what was in flight at its last body, so it cannot go on to more; "
             "start a new --run-dir with the larger total", USAGE)  # fmt: skip
    if args.extend and more:
        console.print(f"extending the run in {run_dir} from {saved.total} to {config.total} "
                      "bodies", highlight=False)  # fmt: skip
        saved = saved.model_copy(update={"total": config.total})
        save_config(run_dir, saved)
        was = saved.model_dump(mode="json")
    elif args.extend:
        fail("--extend: give the run's new total with --set total=N, more than its "
             f"{saved.total}", USAGE)  # fmt: skip
    changed = [key for key in now if was.get(key) != now[key]]
    if changed:
        console.print(f"resuming with the run's saved settings ({', '.join(changed)} differ "
                      "from the profile's today)", highlight=False)  # fmt: skip
    return saved


def _at(settings: dict[str, Any], key: str) -> object:
    """The value at a dotted `key` of nested `settings` (None where there is none)."""
    value: object = settings
    for part in key.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


def coordinator_settings(args: argparse.Namespace, run_dir: Path) -> dict[str, object]:
    """The coordinator's settings in a launch graph (`local_launch`) from `derl run`'s flags."""
    return {"run_dir": run_dir, "profile": args.profile, "env": args.env, "seed": args.seed,
            "settings": [change.text for change in args.set]}  # fmt: skip


def run_nodes(
    nodes: list[NodeCommand],
    run: str,
    endpoint: str,
    config: EvolutionConfig,
    run_dir: Path,
    log_dir: Path,
    resume: str,
    zenoh_config: Path | None = None,
    requeue: Callable[[], str] | None = None,
) -> int:
    """Supervise the nodes of run `run` (its coordinator on `endpoint`) until it is over,
    showing its progress; stopped on SIGTERM or SIGINT, then saying that `resume` resumes it;
    with `requeue`, also on SIGUSR1 (a time limit near), then calling it (it says what it did);
    once done, its best body and fingerprint. The exit status: 0 only when the run finished."""
    supervisor = Supervisor(nodes, log_dir)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: supervisor.stop.set())
    time_up = threading.Event()

    def near_time_limit(*_: object) -> None:
        time_up.set()
        supervisor.stop.set()

    if requeue is not None:
        signal.signal(signal.SIGUSR1, near_time_limit)
    trainers = sum(node.role == "trainer" for node in nodes)
    console.print(
        f"run [bold]{run}[/] ({config.name}, {config.world}): {config.total} bodies, "
        f"{trainers} trainers; coordinator on {endpoint} "
        f"({watch_command(endpoint, run, zenoh_config)}); "
        f"logs in {supervisor.log_dir}",
        highlight=False,
    )
    if not config.in_flight:
        console.print(FREE_RUNNING, highlight=False)
    code, status = supervise(supervisor, run, endpoint, config.total, zenoh_config)
    if code != 0 and requeue is not None and time_up.is_set():
        console.print(requeue(), highlight=False, soft_wrap=True)
        return code
    if code != 0:
        console.print(f"stopped; {resume} resumes the run", highlight=False, soft_wrap=True)
        return code
    best = "-"
    if status is not None and status.best_agent:
        best = f"{status.best_agent} ({status.best_fitness:.1f})"
    born = status.born if status is not None else config.total
    rate = ""
    if status is not None and status.steps_per_s:
        rate = f", {status.steps_per_s:,.0f} env steps/s on average"
    console.print(f"done: {born} bodies, best {best}{rate}; results in {run_dir}")
    console.print(fingerprint_line(load_history(run_dir).fingerprint(), config), highlight=False)
    return 0


def fingerprint_line(fingerprint: str, config: EvolutionConfig) -> str:
    """What `derl run` says of a finished run's fingerprint: that the same profile and seed give
    it again, unless the run was free-running (`FREE_RUNNING`)."""
    claim = ": the same profile and seed give the same on any number of trainers"
    return f"fingerprint {fingerprint} (a hash of the births{claim if config.in_flight else ''})"


def watch_command(endpoint: str, run: str, zenoh_config: Path | None = None) -> str:
    """The monitor's command line for the run at `endpoint` (with the identity in
    `zenoh_config`): bare on the local run's endpoint."""
    if endpoint == local_endpoint() and zenoh_config is None:
        return "derl monitor"
    identity = ("--zenoh-config", str(zenoh_config)) if zenoh_config else ()
    return shlex.join(["derl", "monitor", "--connect", endpoint, "--run", run, *identity])


def listenable(port: int, host: str = "127.0.0.1") -> int:
    """`port` if the coordinator can listen on it at `host`, else exit saying so; for 0 a free
    one outside the ephemeral range (`free_port`: no other node's port 0 takes it before the
    coordinator listens)."""
    if port == 0:
        try:
            return free_port(host)
        except OSError as error:
            fail(f"{error}; choose a port with --port", IN_USE)
    if (refused := bind_error(host, port)) is not None:
        fail(f"cannot listen on {host}:{port}: {refused.strerror} (another run, node or "
             "router?); choose another port with --port", IN_USE)  # fmt: skip
    return port


def local_run_id(run_dir: Path) -> str:
    """The run id of the run (or study) in `run_dir`: its journal's when it has one (it may
    have been started by `derl coordinator --run ID`), else the directory's name."""
    from derl.nodes.journal.history import journal_run

    return journal_run(run_dir) or run_id_of(run_dir.resolve().name)


def run_id_of(name: str) -> str:
    """A run id (a key segment, `ID_PATTERN`, that no command line reads as an option) made of
    a folder's name: accents dropped (`über`: `uber`), any other character a hyphen, none
    leading; a hash of the name where nothing is left."""
    plain = unicodedata.normalize("NFKD", name).encode("ascii", "ignore").decode()
    text = re.sub(r"[^A-Za-z0-9_.-]+", "-", plain).lstrip("-.")[:128].rstrip("-")
    return text or f"run-{hashlib.sha1(name.encode()).hexdigest()[:8]}"


def tensorboard_node(run: str, endpoint: str, logdir: Path) -> NodeCommand:
    """`derl tensorboard` of the run, restarted when it fails; exit if the extra is missing."""
    from derl.nodes.tools.tensorboard import NoTensorBoard, require_extra

    try:
        require_extra()
    except NoTensorBoard as error:
        fail(f"--tensorboard: {error}")
    line = ("tensorboard", "--run", run, "--connect", endpoint, "--logdir", str(logdir))
    return NodeCommand(host="local", name="tensorboard", role="tensorboard", args=line,
                       max_restarts=MAX_RESTARTS)  # fmt: skip


def supervise(
    supervisor: Supervisor, run: str, endpoint: str, total: int, zenoh_config: Path | None = None
) -> tuple[int, RunStatus | None]:
    """Supervise the nodes until the run is over, showing its status (heard on `endpoint`, with
    `zenoh_config`'s identity where given); the supervisor's exit code and the last status seen
    (once the run is done, its rate is `TrainingRate`'s mean)."""
    latest: list[RunStatus] = []
    rate = TrainingRate()
    columns = (
        TextColumn("{task.completed:.0f}/{task.total:.0f} {task.fields[unit]}"),
        TextColumn("best {task.fields[best]}"),
        TextColumn("{task.fields[sps]:,.0f} steps/s"),
        TextColumn("eval {task.fields[evaluated]}"),
    )

    def line(state: dict[str, object]) -> str:  # in a log file (`Shown`)
        return (f"{state['description']}: {state['completed']}/{state['total']} {state['unit']}, "
                f"best {state['best']}, {state['sps']:,.0f} steps/s, "
                f"eval {state['evaluated']}")  # fmt: skip

    fields: dict[str, Any] = {"best": "-", "sps": 0.0, "evaluated": "-", "unit": "born"}
    with (
        open_session(ZenohOptions(connect=(endpoint,), config_file=zenoh_config)) as session,
        Shown(console, "evolution", total, columns, line, **fields) as shown,
    ):
        bus = Bus(session, run)
        bus.subscribe(bus.keys.status(), latest.append, (RunStatus,))

        def show() -> None:
            if not latest:
                return
            s = rate.shown(latest[-1])
            del latest[:-1]
            if s.done:
                supervisor.over.set()
            study = s.target == 0  # a study's progress is its evaluations
            shown.update(
                description="study" if study else "evolution",
                total=s.eval_target if study else s.target,
                completed=s.evaluated if study else s.born,
                best="-" if s.best_fitness is None else f"{s.best_fitness:.1f}",
                sps=s.steps_per_s,
                unit="evaluated" if study else "born",
                evaluated=f"{s.evaluated}/{s.eval_target}",
            )

        code = supervisor.run(poll_s=0.5, tick=show)
    return code, rate.shown(latest[-1]) if latest else None


class TrainingRate:
    """The rate `derl run` shows: the trainers' current env steps/s while the run goes on, and
    once it is done (nothing trains any more, so the current rate is 0) the mean of the rates
    it showed while some worker trained."""

    def __init__(self) -> None:
        self.seen: list[float] = []
        self.last: RunStatus | None = None

    def shown(self, status: RunStatus) -> RunStatus:
        """`status` as shown (each status counts once, however often it is shown)."""
        if status is not self.last and status.steps_per_s > 0:
            self.seen.append(status.steps_per_s)
        self.last = status
        if not status.done or not self.seen:
            return status
        return status.model_copy(update={"steps_per_s": statistics.fmean(self.seen)})
