"""A whole run as the steps of one Slurm job: the graph `derl slurm` (launch/slurm/derl-run.sbatch)
supervises.

The job's task slots (``--ntasks`` as Slurm spread them over its nodes, every component of a
heterogeneous job in turn, each slot with the component's ``--cpus-per-task``) are filled in
order: the first by the coordinator, which runs in the batch step on the job's first node (where
the batch script runs), the next by the evaluator when the profile evaluates, every other by a
trainer whose threads are its slot's CPUs. These are the nodes of `derl run`
(`nodes.launch.local`), spread over the job's nodes; each worker runs as an ``srun --exact`` step
of one task on its slot's node (``--het-group`` in a heterogeneous job), and `Supervisor`
restarts a worker whose process dies or whose step is cancelled (policy ``always``: a worker
stopped by a signal exits 0), as a new step with a new node id.

Node ids are ``j<job>a<attempt><token>-<node>-<role>-<k>``: the job id, its restart count
(``SLURM_RESTART_COUNT``: a requeue or a preemption) and a token drawn at each start, so no two
jobs, attempts or clusters (whose job ids start again at 1) share one; with certificates every
start issues one identity per node from the user's CA. The coordinator listens on a free port of
the first node's address (Slurm's NodeAddr), every worker on a free port of its own node's: two
jobs on one node never collide.
"""

from __future__ import annotations

import re
import secrets
import shutil
import socket
import string
import subprocess
import sys
from collections.abc import Callable, Mapping
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

from pydantic import BaseModel, ConfigDict, Field, model_validator

from derl.nodes.launch.commands import NodeCommand, build_commands
from derl.nodes.launch.local import local_launch
from derl.nodes.launch.model import LaunchFile, NodeSpec

TOKEN_CHARS = string.ascii_lowercase + string.digits
COUNT = re.compile(r"^(\d+)(?:\(x(\d+)\))?$")  # one item of SLURM_TASKS_PER_NODE: 2 or 2(x3)


class Slot(NamedTuple):
    """One task of the job: the node it is on, its het group (None in a plain job), its CPUs."""

    node: str
    group: int | None
    cpus: int


class JobGroup(BaseModel):
    """One component of the job (the job itself unless it is heterogeneous)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    index: int | None = Field(description="het group (`--het-group`); None: a plain job")
    nodes: list[str] = Field(min_length=1, description="its nodes, in Slurm's order")
    tasks: list[int] = Field(min_length=1, description="tasks on each of its nodes")
    cpus_per_task: int = Field(1, ge=1, description="CPUs of each task")

    @model_validator(mode="after")
    def _a_count_per_node(self) -> JobGroup:
        if len(self.tasks) != len(self.nodes):
            raise ValueError(f"{len(self.tasks)} task counts for {len(self.nodes)} nodes")
        return self

    def slots(self) -> list[Slot]:
        return [Slot(node, self.index, self.cpus_per_task)
                for node, count in zip(self.nodes, self.tasks, strict=True)
                for _ in range(count)]  # fmt: skip


class SlurmJob(BaseModel):
    """What `derl slurm` needs of the job it runs in (`job_from_environment`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    id: str = Field(pattern=r"^\d+$", description="SLURM_JOB_ID")
    attempt: int = Field(0, ge=0, description="SLURM_RESTART_COUNT: requeues and preemptions")
    groups: list[JobGroup] = Field(min_length=1, description="its components")

    def slots(self) -> list[Slot]:
        return [slot for group in self.groups for slot in group.slots()]

    @property
    def first_node(self) -> str:
        """Where the batch script, and so the coordinator, runs."""
        return self.groups[0].nodes[0]


def tasks_per_node(text: str) -> list[int]:
    """SLURM_TASKS_PER_NODE (``2(x3),1``) as a count per node (``[2, 2, 2, 1]``)."""
    counts = []
    for item in text.split(","):
        match = COUNT.match(item.strip())
        if match is None:
            raise ValueError(f"{text!r} is not a SLURM_TASKS_PER_NODE such as 2(x3),1")
        counts += [int(match[1])] * int(match[2] or 1)
    return counts


def job_from_environment(env: Mapping[str, str], hostnames: Callable[[str], list[str]]) -> SlurmJob:
    """The job this process runs in, from its Slurm variables (`hostnames` expands a node list
    such as ``n[1-3]``); ValueError saying what is missing outside a job."""
    if "SLURM_JOB_ID" not in env:
        raise ValueError(
            "not in a Slurm job (no SLURM_JOB_ID): submit it, e.g. `sbatch --nodes=2 --ntasks=8 "
            "launch/slurm/derl-run.sbatch --profile demo`"
        )
    size = int(env.get("SLURM_HET_SIZE", "0"))
    suffixes = [(g, f"_HET_GROUP_{g}") for g in range(size)] if size else [(None, "")]
    groups = []
    for index, suffix in suffixes:
        nodes = env.get(f"SLURM_JOB_NODELIST{suffix}")
        tasks = env.get(f"SLURM_TASKS_PER_NODE{suffix}")
        if not nodes or not tasks:
            raise ValueError(f"SLURM_JOB_NODELIST{suffix} or SLURM_TASKS_PER_NODE{suffix} unset")
        cpus = int(env.get(f"SLURM_CPUS_PER_TASK{suffix}", "1"))
        groups.append(JobGroup(index=index, nodes=hostnames(nodes), tasks=tasks_per_node(tasks),
                               cpus_per_task=cpus))  # fmt: skip
    return SlurmJob(id=env["SLURM_JOB_ID"], attempt=int(env.get("SLURM_RESTART_COUNT", "0")),
                    groups=groups)  # fmt: skip


def hostnames(nodelist: str) -> list[str]:
    """A Slurm node list (``n[1-3],gpu7``) as node names, by `scontrol show hostnames`."""
    return _scontrol("show", "hostnames", nodelist).split()


def node_addresses(nodes: list[str]) -> dict[str, str]:
    """Each node's IP address: its NodeAddr (what Slurm itself connects to) resolved here."""
    text = _scontrol("show", "node", "--oneliner", ",".join(nodes))
    found = dict(re.findall(r"NodeName=(\S+) .*?NodeAddr=(\S+)", text))
    missing = sorted(set(nodes) - set(found))
    if missing:
        raise ValueError(f"scontrol shows no NodeAddr of {', '.join(missing)}")
    try:
        return {node: socket.gethostbyname(found[node]) for node in nodes}
    except OSError as error:
        raise ValueError(f"cannot resolve a node's address: {error}") from None


def _scontrol(*args: str) -> str:
    try:
        done = subprocess.run(["scontrol", *args], capture_output=True, text=True, timeout=60)
    except OSError as error:
        raise ValueError(f"scontrol: {error.strerror}") from None
    if done.returncode:
        raise ValueError(f"scontrol {' '.join(args)}: {done.stderr.strip()}")
    return done.stdout


def attempt_tag(job: SlurmJob, token: str | None = None) -> str:
    """The prefix of this start's node ids: job id, restart count and a random token."""
    token = token or "".join(secrets.choice(TOKEN_CHARS) for _ in range(3))
    return f"j{job.id}a{job.attempt}{token}"


def slurm_launch(
    job: SlurmJob,
    addresses: Mapping[str, str],
    run: str,
    port: int,
    tag: str,
    evaluators: int,
    certs: Path | None = None,
    **coordinator: object,
) -> LaunchFile:
    """The graph of `derl run` (`local_launch`) over the job's slots: the coordinator listening
    on `port` of the first node's address, `evaluators` (0 or 1) evaluators, a trainer in every
    other slot; workers restart `always`. `certs`: the folder of this start's identities (then
    every endpoint is TLS). `coordinator`: its settings (`run_dir`, `profile`, `env`, ...)."""
    slots = job.slots()
    trainers = len(slots) - 1 - evaluators
    if trainers < 1:
        raise ValueError(
            f"{len(slots)} tasks hold the coordinator{' and the evaluator' * evaluators} and no "
            f"trainer: submit with --ntasks={2 + evaluators} or more"
        )
    proto = "tls" if certs else "tcp"
    endpoint = f"{proto}/{addresses[job.first_node]}:{port}"
    workers = {"trainer": trainers, "evaluator": evaluators}
    local = local_launch(run, endpoint, workers, None, **coordinator)  # None: no --tensorboard
    specs: dict[str, NodeSpec] = {spec.role: spec for host in local.hosts for spec in host.nodes}
    roles = ["coordinator", *["evaluator"] * evaluators, *["trainer"] * trainers]
    hosts: dict[str, dict] = {}
    for slot, role in zip(slots, roles, strict=True):
        host = hosts.setdefault(slot.node, {
            "name": host_name(tag, slot.node),
            "address": addresses[slot.node],
            "listen": f"{proto}/{addresses[slot.node]}:0",  # a free port for each worker
            "derl": derl_command(),
            "nodes": [],
        })  # fmt: skip
        spec = specs[role].model_dump()
        if role != "coordinator":
            spec.update(restart="always", threads=slot.cpus, listen=None)
        previous = host["nodes"][-1] if host["nodes"] else None
        if previous is not None and previous["role"] == role and role != "coordinator":
            previous["count"] += 1
        else:
            host["nodes"].append({**spec, "count": 1})
    data = local.model_dump()
    data.update(hosts=list(hosts.values()), certs=certs)
    return LaunchFile.model_validate(data)


def host_name(tag: str, node: str) -> str:
    """The launch graph's host of a Slurm node: the start's tag and the node's name."""
    return f"{tag}-{re.sub(r'[^A-Za-z0-9_.-]', '-', node)}"


def derl_command() -> str:
    """The `derl` command the job's steps run: the one beside this Python, else on PATH."""
    here = shutil.which("derl", path=str(Path(sys.executable).parent))
    return here or shutil.which("derl") or "derl"


def job_commands(graph: LaunchFile, job: SlurmJob, tag: str) -> list[NodeCommand]:
    """Every node process of `graph`: the coordinator here (in the batch step), every worker as
    one ``srun --exact`` step of one task on its slot's node."""
    groups = {host_name(tag, slot.node): slot for slot in job.slots()}
    commands = []
    for command in build_commands(graph):
        if command.role != "coordinator":
            command = replace(command, launcher=srun_line(command.name, groups[command.host]))
        commands.append(command)
    return commands


def srun_line(name: str, slot: Slot) -> tuple[str, ...]:
    """The ``srun`` that runs one node as a step of this job on `slot`'s node, named `name`:
    exactly its slot's CPUs (``--exact``: else the first step takes the whole allocation and
    the next waits for ever), the job's memory on the node shared with the other steps
    (``--mem=0``: else under ``sbatch --mem`` the first step takes all of it)."""
    het = () if slot.group is None else (f"--het-group={slot.group}",)
    return ("srun", "--exact", "--nodes=1", "--ntasks=1", f"--cpus-per-task={slot.cpus}",
            "--mem=0", f"--nodelist={slot.node}", f"--job-name={name}", "--mpi=none",
            *het)  # fmt: skip
