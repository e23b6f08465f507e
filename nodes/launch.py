"""Launch files: which nodes of a run start on which host, and `derl launch` that starts them.

A launch file (YAML, validated by `LaunchFile`, unknown keys are errors) names the run, its
profile, the Zenoh topology and, per host, the nodes to start with their counts and restart
policy::

    run: exp1
    run_dir: runs/exp1
    profile: demo                  # a built-in profile or a profile YAML file
    topology: {kind: peer_mesh, seed: "tcp/10.0.0.5:7447"}     # or {kind: router, endpoint, host}
    zenoh_config: launch/zenoh/tls-acl.json5                   # optional (TLS, access control)
    hosts:
      - name: head
        listen: "tcp/10.0.0.5:7447"
        nodes: [{role: coordinator}]
      - name: gpu1
        address: gpu1.example.org
        ssh: true                  # or "user@gpu1.example.org"
        listen: "tcp/10.0.0.6:7447"
        nodes: [{role: trainer, count: 8, restart: on-failure, max_restarts: 5}]

`build_commands` turns it into the exact ``derl ...`` command line of every node process (one
process per unit of `count`; workers get the name ``<host>-<role>-<k>``, ``.r<n>`` after the
n-th restart). `derl launch FILE` starts this host's processes (`plan`: the host named ``local``
or after this machine, else every host without ``ssh``) and, for each ``ssh`` host, one
``ssh -tt HOST 'cd WORKDIR && exec derl launch FILE --host NAME'`` that starts that host's nodes
there (so the launch file must be at the same path under WORKDIR). `Supervisor` restarts
processes by their policy (back-off 1, 2, 4 ... 30 s) and stops them all on Ctrl-C, SIGTERM or
SIGHUP (an ssh session that ends), or when the coordinator finishes the run. Local processes run
with this Python (``python -m nodes.cli``, the same as ``derl``).

Endpoints: in a peer mesh every process listens on its host's ``listen`` endpoint (process k of
the host on port + k, or on port 0 when the port is 0) and connects to the seed, except the
process that is the seed; gossip completes the mesh. In a router topology the router host runs
``derl router`` on the router endpoint and every other node is a Zenoh client of it.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import shlex
import signal
import socket
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from messages.types import ID_PATTERN

log = logging.getLogger("derl.launch")

ROLES = ("router", "coordinator", "trainer", "evaluator")  # also the start order on a host
LOCAL_ADDRESSES = {"localhost", "local", "127.0.0.1", "::1"}
WILDCARD_HOSTS = {"0.0.0.0", "[::]", "::"}
_ENDPOINT = re.compile(
    r"^(?P<proto>[a-z][a-z0-9-]*)/(?P<host>\[[^\]]+\]|[^/:\[\]]+):(?P<port>\d+)$"
)
RESTART_DELAY_S = 1.0
MAX_RESTART_DELAY_S = 30.0
SSH = ("ssh", "-tt", "-o", "BatchMode=yes")  # a tty: the remote node gets SIGHUP when ssh ends

Id = Annotated[str, Field(pattern=ID_PATTERN)]


def _check_endpoint(value: str) -> str:
    match = _ENDPOINT.match(value)
    if not match or not 0 <= int(match["port"]) <= 65535:
        raise ValueError(
            f"{value!r} is not a Zenoh endpoint PROTO/HOST:PORT such as tcp/10.0.0.5:7447 "
            "or tls/head.example.org:7447"
        )
    return value


Endpoint = Annotated[str, AfterValidator(_check_endpoint)]


def split_endpoint(endpoint: str) -> tuple[str, str, int]:
    """(protocol, host, port) of a checked endpoint."""
    match = _ENDPOINT.match(endpoint)
    if match is None:
        raise ValueError(f"not an endpoint: {endpoint!r}")
    return match["proto"], match["host"], int(match["port"])


def with_port(endpoint: str, port: int) -> str:
    proto, host, _ = split_endpoint(endpoint)
    return f"{proto}/{host}:{port}"


# --- the file ------------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class NodeSpec(_Strict):
    """`count` processes of one role on a host."""

    role: Literal["coordinator", "trainer", "evaluator", "router"]
    count: int = Field(1, ge=1, le=4096)
    threads: int = Field(1, ge=1, le=4096, description="simulation threads of each worker")
    restart: Literal["never", "on-failure", "always"] = "on-failure"
    max_restarts: int = Field(3, ge=0, description="restarts of each process, at most")


class PeerMesh(_Strict):
    """Every node is a Zenoh peer: it listens on its host's endpoint and connects to `seed`."""

    kind: Literal["peer_mesh"]
    seed: Endpoint


class RouterTopology(_Strict):
    """`derl router` on host `host` at `endpoint`; every node is a Zenoh client of it."""

    kind: Literal["router"]
    endpoint: Endpoint
    host: Id


class HostSpec(_Strict):
    name: Id
    address: str = Field("localhost", min_length=1, description="for ssh; localhost = this host")
    ssh: bool | str = Field(False, description="start its nodes over ssh (true, or user@host)")
    listen: Endpoint | None = Field(None, description="where this host's nodes listen (mesh)")
    workdir: str | None = Field(None, description="directory the nodes start in (ssh hosts)")
    derl: str = Field("derl", min_length=1, description="the derl command on this host")
    zenoh_config: Path | None = Field(None, description="this host's Zenoh config (certificates)")
    nodes: list[NodeSpec] = Field(default_factory=list)

    @property
    def local_address(self) -> bool:
        return self.address in LOCAL_ADDRESSES

    @property
    def remote(self) -> str | None:
        """The ssh target when this host's nodes are started over ssh, else None."""
        if self.ssh is False or (self.ssh is True and self.local_address):
            return None
        return self.address if self.ssh is True else str(self.ssh)


class LaunchFile(_Strict):
    run: Id
    run_dir: Path
    profile: str = Field("smoke", min_length=1, description="smoke | demo | paper | FILE.yaml")
    env: Literal["ft", "vt", "mvt"] | None = Field(None, description="world (overrides profile)")
    topology: Annotated[PeerMesh | RouterTopology, Field(discriminator="kind")]
    zenoh_config: Path | None = Field(None, description="Zenoh JSON5 config of every node")
    hosts: list[HostSpec] = Field(min_length=1)

    @model_validator(mode="after")
    def _consistent(self) -> LaunchFile:
        names = [h.name for h in self.hosts]
        if duplicated := sorted({n for n in names if names.count(n) > 1}):
            raise ValueError(f"host names must be unique: {', '.join(duplicated)} repeated")
        coordinators = [
            (h.name, n.count) for h in self.hosts for n in h.nodes if n.role == "coordinator"
        ]
        if sum(count for _, count in coordinators) != 1:
            raise ValueError(
                f"a run has exactly one coordinator (count 1); this file has "
                f"{sum(count for _, count in coordinators)}"
            )
        routers = [(h.name, n.count) for h in self.hosts for n in h.nodes if n.role == "router"]
        if isinstance(self.topology, RouterTopology):
            if self.topology.host not in names:
                raise ValueError(f"router host {self.topology.host!r} is not among the hosts")
            if routers != [(self.topology.host, 1)]:
                raise ValueError(
                    f"the router topology needs one node `role: router` (count 1) on host "
                    f"{self.topology.host!r}, and no other router; found {routers or 'none'}"
                )
        else:
            if routers:
                raise ValueError("`role: router` nodes need `topology: {kind: router, ...}`")
            for host in self.hosts:
                if host.nodes and host.listen is None and not host.local_address:
                    raise ValueError(
                        f"host {host.name!r}: in a peer mesh every host needs a `listen` "
                        "endpoint the other hosts can reach (peers without one do not mesh)"
                    )
            if not any("--connect" not in c.args for c in build_commands(self)):
                raise ValueError(
                    f"no node listens on the seed {self.topology.seed}: give the seed's host "
                    f"`listen: {self.topology.seed}` (its first node is the seed)"
                )
        return self

    def host(self, name: str) -> HostSpec:
        for host in self.hosts:
            if host.name == name:
                return host
        raise KeyError(
            f"no host {name!r} in this launch file; hosts: {[h.name for h in self.hosts]}"
        )


def load(path: Path) -> LaunchFile:
    """The launch file at `path`, or ValueError saying what is wrong with it."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as error:
        raise ValueError(f"{path}: {error}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: a launch file is a mapping (run, run_dir, topology, hosts ...)")
    try:
        return LaunchFile.model_validate(data)
    except ValidationError as error:
        raise ValueError(f"{path} is not a valid launch file:\n{error}") from None


# --- commands ------------------------------------------------------------------------------


@dataclass(frozen=True)
class NodeCommand:
    """One process the launcher starts: a node (`derl ROLE ...`) or, for an ssh host, the
    launcher of that host's nodes there (`ssh HOST 'cd DIR && exec derl launch FILE --host H'`)."""

    host: str
    name: str  # unique in the launch: <host>-<role>-<k>, or <host>-ssh
    role: str  # a node role, or "ssh"
    args: tuple[str, ...]  # after `derl`
    remote: str | None = None  # ssh target
    workdir: str | None = None
    derl: str = "derl"
    restart: str = "on-failure"
    max_restarts: int = 3
    order: int = 0  # start order: router, coordinator, trainers, evaluators
    runs: tuple[NodeCommand, ...] = ()  # what an ssh launcher starts there

    def derl_args(self, restarts: int = 0) -> list[str]:
        """The arguments of the `restarts`-th start: a restarted worker gets a new node id."""
        args = list(self.args)
        if restarts and self.role in ("trainer", "evaluator") and "--name" in args:
            i = args.index("--name") + 1
            args[i] = f"{args[i]}.r{restarts}"
        return args

    def argv(self, restarts: int = 0) -> list[str]:
        """What the launcher executes: the derl line, or ssh with it."""
        line = [self.derl, *self.derl_args(restarts)]
        if self.remote is None:
            return line
        workdir = self.workdir or os.getcwd()
        return [*SSH, self.remote, f"cd {shlex.quote(workdir)} && exec {shlex.join(line)}"]

    def shell(self, restarts: int = 0) -> str:
        return shlex.join(self.argv(restarts))


def build_commands(launch: LaunchFile, hosts: list[str] | None = None) -> list[NodeCommand]:
    """Every node process of `hosts` (default: all) as started on its own host, in start order
    (router, coordinator, workers; within a host, the order of its node list)."""
    chosen = launch.hosts if hosts is None else [launch.host(name) for name in hosts]
    commands = [command for host in chosen for command in _host_commands(launch, host)]
    return sorted(commands, key=lambda c: c.order)


def _host_commands(launch: LaunchFile, host: HostSpec) -> list[NodeCommand]:
    commands = []
    process = 0  # index of the process on this host (listen port offset)
    for spec in host.nodes:
        for k in range(spec.count):
            name = f"{host.name}-{spec.role}-{k}"
            args = [spec.role, *_role_args(launch, spec, name), *_bus_args(launch, host, process)]
            commands.append(
                NodeCommand(
                    host=host.name,
                    name=name,
                    role=spec.role,
                    args=tuple(args),
                    derl=host.derl,
                    restart=spec.restart,
                    max_restarts=spec.max_restarts,
                    order=ROLES.index(spec.role),
                )
            )
            process += 1
    return commands


def ssh_command(launch: LaunchFile, file: Path, host: HostSpec) -> NodeCommand:
    """The launcher of `host`'s nodes, started there over ssh; it restarts them there."""
    runs = tuple(_host_commands(launch, host))
    return NodeCommand(
        host=host.name,
        name=f"{host.name}-ssh",
        role="ssh",
        args=("launch", str(file), "--host", host.name),
        remote=host.remote,
        workdir=host.workdir,
        derl=host.derl,
        restart="on-failure",  # a dropped connection: start the host's launcher again
        max_restarts=max((spec.max_restarts for spec in host.nodes), default=0),
        order=min((c.order for c in runs), default=len(ROLES)),
        runs=runs,
    )


def _role_args(launch: LaunchFile, spec: NodeSpec, name: str) -> list[str]:
    if spec.role == "coordinator":
        env = ["--env", launch.env] if launch.env else []
        return ["--run", launch.run, "--profile", launch.profile, *env, "--run-dir",
                str(launch.run_dir)]  # fmt: skip
    if spec.role == "router":
        return []
    return ["--run", launch.run, "--name", name, "--threads", str(spec.threads)]


def _bus_args(launch: LaunchFile, host: HostSpec, process: int) -> list[str]:
    config = host.zenoh_config or launch.zenoh_config
    args = ["--zenoh-config", str(config)] if config else []
    topology = launch.topology
    if isinstance(topology, RouterTopology):
        if host.name == topology.host and process == _router_index(host):
            return ["--listen", host.listen or topology.endpoint, *args]
        return ["--mode", "client", "--connect", topology.endpoint, *args]
    listen = host.listen or "tcp/127.0.0.1:0"
    _, _, port = split_endpoint(listen)
    listen = with_port(listen, port + process if port else 0)
    connect = [] if _is_seed(listen, host, topology.seed) else ["--connect", topology.seed]
    return ["--listen", listen, *connect, *args]


def _router_index(host: HostSpec) -> int:
    index = 0
    for spec in host.nodes:
        if spec.role == "router":
            return index
        index += spec.count
    return -1


def _is_seed(listen: str, host: HostSpec, seed: str) -> bool:
    """Whether the process listening on `listen` is the mesh's seed (it connects to nobody)."""
    if listen == seed:
        return True
    proto, listen_host, port = split_endpoint(listen)
    seed_proto, seed_host, seed_port = split_endpoint(seed)
    return (
        (proto, port) == (seed_proto, seed_port)
        and listen_host in WILDCARD_HOSTS
        and host.address == seed_host
    )


def plan(
    launch: LaunchFile, file: Path, hosts: list[str] | None = None, ssh: bool = True
) -> list[NodeCommand]:
    """What `derl launch FILE` starts: the nodes of `hosts` here (never over ssh), or by
    default this host's nodes here and one launcher per ssh host over ssh."""
    if hosts:
        return build_commands(launch, hosts)
    commands = build_commands(launch, local_hosts(launch))
    if ssh:
        commands += [ssh_command(launch, file, launch.host(name)) for name in remote_hosts(launch)]
    return sorted(commands, key=lambda c: c.order)


def dry_run_text(commands: list[NodeCommand]) -> str:
    """Every command, grouped by host; for an ssh host, also the nodes it starts there."""
    lines, host = [], None
    for command in commands:
        if command.host != host:
            host = command.host
            where = f"over ssh ({command.remote})" if command.remote else "on this host"
            lines.append(f"# host {host}: {where}")
        lines.append(command.shell())
        lines += [f"#   there: {node.shell()}" for node in command.runs]
    return "\n".join(lines)


# --- which hosts are this one --------------------------------------------------------------


def this_host_names() -> set[str]:
    full = socket.gethostname()
    return {"local", full, full.split(".")[0], socket.getfqdn()}


def local_hosts(launch: LaunchFile) -> list[str]:
    """The hosts whose nodes this machine starts by default: the host named `local` or after
    this machine, else every host that is not started over ssh."""
    names = this_host_names()
    mine = [
        h.name for h in launch.hosts if h.remote is None and (h.name in names or h.address in names)
    ]
    return mine or [h.name for h in launch.hosts if h.remote is None]


def remote_hosts(launch: LaunchFile) -> list[str]:
    return [h.name for h in launch.hosts if h.remote is not None]


# --- running them --------------------------------------------------------------------------


@dataclass
class _Slot:
    command: NodeCommand
    process: subprocess.Popen | None = None
    restarts: int = 0
    due: float | None = None  # when a pending restart is due
    finished: bool = False
    returncode: int | None = None


class Supervisor:
    """Starts node processes, restarts them by their policy, stops them all at the end."""

    def __init__(self, commands: list[NodeCommand], log_dir: Path) -> None:
        self.slots = [_Slot(command) for command in commands]
        self.log_dir = Path(log_dir)
        self.stop = threading.Event()

    def _start(self, slot: _Slot) -> None:
        from nodes.processes import spawn_derl

        command = slot.command
        log_file = self.log_dir / f"{command.name}.log"
        with log_file.open("ab") as out:
            out.write(
                f"--- derl launch, start {slot.restarts}: {command.shell(slot.restarts)}\n".encode()
            )
        if command.remote is None:
            slot.process = spawn_derl(command.derl_args(slot.restarts), log_file)
        else:
            slot.process = _spawn(command.argv(slot.restarts), log_file)
        slot.due = slot.returncode = None
        log.info("%s started (pid %d)%s", command.name, slot.process.pid,
                 f", restart {slot.restarts}" if slot.restarts else "")  # fmt: skip

    def run(self, poll_s: float = 0.25) -> int:
        """Start everything, supervise until the run is over or `stop` is set; the exit code:
        0 when the run finished (or every node ended cleanly), 1 when a node failed for good,
        130 when stopped."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        code = None
        try:
            for slot in self.slots:
                if not self.stop.is_set():
                    self._start(slot)
            while code is None and not self.stop.wait(poll_s):
                code = self._step(time.monotonic())
        finally:
            self.shutdown()
        return 130 if code is None else code

    def _step(self, now: float) -> int | None:
        """One supervision round; the exit code when there is nothing left to supervise."""
        for slot in self.slots:
            if slot.finished:
                continue
            if slot.due is not None:
                if now >= slot.due:
                    self._start(slot)
                continue
            if slot.process is None or slot.process.poll() is None:
                continue
            slot.returncode = code = slot.process.returncode
            command = slot.command
            if command.role == "coordinator" and code == 0:
                log.info("the coordinator finished the run: stopping this host's nodes")
                slot.finished = True
                return 0
            wanted = command.restart == "always" or (command.restart == "on-failure" and code != 0)
            if wanted and slot.restarts < command.max_restarts:
                slot.restarts += 1
                delay = min(RESTART_DELAY_S * 2 ** (slot.restarts - 1), MAX_RESTART_DELAY_S)
                slot.due = now + delay
                log.warning("%s exited with %s: restart %d/%d in %.0f s", command.name, code,
                            slot.restarts, command.max_restarts, delay)  # fmt: skip
                continue
            slot.finished = True
            level = logging.INFO if code == 0 else logging.WARNING
            log.log(level, "%s exited with %s (restart: %s, %d restarts done)",
                    command.name, code, command.restart, slot.restarts)  # fmt: skip
            if command.role == "coordinator":
                log.error("the coordinator failed for good: stopping this host's nodes")
                return 1
        if all(slot.finished for slot in self.slots):
            return 0 if all(slot.returncode == 0 for slot in self.slots) else 1
        return None

    def shutdown(self) -> None:
        """SIGTERM every node still running (SIGKILL after 10 s); no restarts after this."""
        from nodes.processes import stop_all

        stop_all([s.process for s in self.slots if s.process is not None], timeout=10)


def _spawn(argv: list[str], log_file: Path) -> subprocess.Popen:
    """Start a non-derl command (ssh) like `spawn_derl` does: own process group, dies with us."""
    from nodes.processes import _child_setup

    with log_file.open("ab") as out:
        return subprocess.Popen(
            argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            preexec_fn=_child_setup,
        )  # fmt: skip


# --- the command ---------------------------------------------------------------------------


def main(args: argparse.Namespace) -> int:
    """`derl launch` (arguments as `nodes.launch_cli` parses them); the exit code."""
    try:
        launch = load(args.file)
        commands = plan(launch, args.file, args.host, ssh=not args.no_ssh)
    except ValueError as error:
        raise SystemExit(f"derl launch: {error}") from None
    except KeyError as error:
        raise SystemExit(f"derl launch: {error.args[0]}") from None
    if not commands:
        raise SystemExit(f"derl launch: no nodes to start from {args.file} on this host")
    if args.dry_run:
        print(dry_run_text(commands))
        return 0
    if any(c.role == "coordinator" and c.remote is None for c in commands):
        from nodes.bus_cli import profile_from

        profile_from(argparse.Namespace(profile=launch.profile, env=launch.env))  # fail early
    supervisor = Supervisor(commands, args.log_dir or launch.run_dir / "logs")
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):  # SIGHUP: our ssh session ended
        signal.signal(sig, lambda *_: supervisor.stop.set())
    hosts = sorted({c.host for c in commands})
    log.info("run %s: %d node processes of %s; logs in %s", launch.run, len(commands),
             ", ".join(hosts), supervisor.log_dir)  # fmt: skip
    return supervisor.run()
