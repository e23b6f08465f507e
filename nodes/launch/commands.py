"""The command line of every node process of a launch file, and which hosts are this one.

`build_commands` turns a `LaunchFile` into the exact ``derl ...`` command line of every node
process (one process per unit of `count`; workers get the name ``<host>-<role>-<k>``, ``.r<n>``
after the n-th restart). `plan` says what `derl launch FILE` starts: this host's processes (the
host named ``local`` or after this machine, else every host without ``ssh``) and, for each
``ssh`` host, one ``ssh -tt HOST 'cd WORKDIR && exec derl launch FILE --host NAME'`` that starts
that host's nodes there (so the launch file must be at the same path under WORKDIR).

Endpoints: in a peer mesh every process listens where its host says (`HostSpec.mesh_endpoints`)
and connects to the seed, except the process that is the seed; gossip completes the mesh. In a
router topology the router host runs ``derl router`` on the router endpoint and every other node
is a Zenoh client of it.
"""

from __future__ import annotations

import os
import shlex
import socket
from dataclasses import dataclass
from pathlib import Path

from derl.nodes.launch.model import (
    ROLES,
    HostSpec,
    LaunchFile,
    NodeSpec,
    RouterTopology,
    is_seed,
)

SSH = ("ssh", "-tt", "-o", "BatchMode=yes")  # a tty: the remote node gets SIGHUP when ssh ends


NODE_CONFIG = "zenoh.json5"  # a node's Zenoh config in its `derl certs` folder


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
    launcher: tuple[str, ...] = ()  # what the node runs under (`srun ...`: a Slurm job step)

    def derl_args(self, restarts: int = 0) -> list[str]:
        """The arguments of the `restarts`-th start: a restarted worker gets a new node id."""
        args = list(self.args)
        if restarts and self.role in ("trainer", "evaluator") and "--name" in args:
            i = args.index("--name") + 1
            args[i] = f"{args[i]}.r{restarts}"
        return args

    def argv(self, restarts: int = 0) -> list[str]:
        """What the launcher executes: the derl line, under `launcher` (srun), or ssh with it."""
        line = [*self.launcher, self.derl, *self.derl_args(restarts)]
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
    process = 0  # index of the process on this host
    listens = host.mesh_endpoints()
    for spec in host.nodes:
        for k in range(spec.count):
            name = f"{host.name}-{spec.role}-{k}"
            args = [
                spec.role,
                *_role_args(launch, spec, name),
                *_bus_args(launch, host, process, name, listens[process]),
            ]
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
    if spec.role == "coordinator" and launch.study is not None:
        study = ["--run", launch.run, "--study", str(launch.study)]
        if launch.study_runs:
            study += ["--profile", launch.profile, "--study-runs", *map(str, launch.study_runs)]
        return study
    if spec.role == "coordinator":
        env = ["--env", launch.env] if launch.env else []
        seed = ["--seed", str(launch.seed)] if launch.seed is not None else []
        settings = [part for text in launch.settings for part in ("--set", text)]
        return ["--run", launch.run, "--profile", launch.profile, *settings, *env, *seed,
                "--run-dir", str(launch.run_dir)]  # fmt: skip
    if spec.role == "router":
        return []
    board = ["--tensorboard", str(spec.tensorboard)] if spec.tensorboard is not None else []
    return ["--run", launch.run, "--name", name, "--threads", str(spec.threads), *board]


def _bus_args(
    launch: LaunchFile, host: HostSpec, process: int, name: str, listen: str
) -> list[str]:
    config = host.zenoh_config or launch.zenoh_config
    if launch.certs is not None:
        config = launch.certs / name / NODE_CONFIG  # its own identity (`derl certs`)
    args = ["--zenoh-config", str(config)] if config else []
    topology = launch.topology
    if isinstance(topology, RouterTopology):
        if host.name == topology.host and process == _router_index(host):
            return ["--listen", host.listen or topology.endpoint, *args]
        return ["--mode", "client", "--connect", topology.endpoint, *args]
    connect = [] if is_seed(listen, host, topology.seed) else ["--connect", topology.seed]
    return ["--listen", listen, *connect, *args]


def _router_index(host: HostSpec) -> int:
    index = 0
    for spec in host.nodes:
        if spec.role == "router":
            return index
        index += spec.count
    return -1


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
