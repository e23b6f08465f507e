"""`derl slurm`: a whole run as the steps of the Slurm job it runs in
(launch/slurm/derl-run.sbatch; the graph: `nodes.launch.slurm`).

It takes `derl run`'s arguments and runs as `derl run` does (`run_nodes`: supervised nodes,
progress, the fingerprint once done), with the coordinator here in the batch step and every
worker as a step of the job. The exit status is the run's: 0 only when the run finished, so
`sbatch --dependency=afterok:JOB` chains what needs a finished run. A requeue or a preemption
starts it again on the same run directory: the run resumes from its journal, each start with its
own node ids and logs (RUN_DIR/logs/slurm-<job>-<restart count>/). Near the time limit (SIGUSR1)
it stops its nodes and requeues its own job (`_requeue`).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
from pathlib import Path

from derl.nodes.cli.options import add_profile_arguments, fail, port_number, profile_from
from derl.nodes.cli.run import (
    add_extend_argument,
    coordinator_settings,
    listenable,
    local_run_id,
    run_directory_of,
    run_nodes,
)
from derl.nodes.launch.commands import NODE_CONFIG
from derl.nodes.launch.identities import MONITOR, issue_identities, load_ca
from derl.nodes.launch.model import LaunchFile, PeerMesh
from derl.nodes.launch.slurm import (
    attempt_tag,
    hostnames,
    job_commands,
    job_from_environment,
    node_addresses,
    slurm_launch,
)

REQUEUE_S = 30  # for `scontrol requeue`


def register(commands: argparse._SubParsersAction) -> None:
    slurm = commands.add_parser(
        "slurm",
        help="run evolution as the steps of this Slurm job (launch/slurm/derl-run.sbatch)",
        description="Inside a Slurm job (`sbatch launch/slurm/derl-run.sbatch ARGS`): the "
        "coordinator here, the evaluator in the second task and a trainer in each other one, as "
        "`srun --exact` steps, each restarted when it dies or its step is cancelled; on SIGUSR1 "
        "(the script's --signal=B:USR1@120, before the time limit) it stops them and requeues "
        "the job. Exit status 0 only when the run finished.",
    )
    add_profile_arguments(slurm)
    slurm.add_argument(
        "--run-dir",
        type=Path,
        help="on a file system every node of the job reads (default: runs/<profile>-<world>"
        "[-s<seed>][-<KEY=VALUE>...])",
    )
    add_extend_argument(slurm)
    slurm.add_argument(
        "--port",
        type=port_number,
        default=0,
        help="the coordinator's port on the first node (default 0: a free one at each start)",
    )
    slurm.add_argument(
        "--certs",
        type=Path,
        metavar="CA_DIR",
        help="TLS: the CA of `derl certs --out CA_DIR` (ca.pem, ca.key); each start issues one "
        "identity per node, and a monitor's, in RUN_DIR/certs",
    )
    slurm.set_defaults(handler=_slurm)


def _slurm(args: argparse.Namespace) -> int:
    config = profile_from(args)
    try:
        job = job_from_environment(os.environ, hostnames)
        addresses = node_addresses(list(dict.fromkeys(slot.node for slot in job.slots())))
    except ValueError as error:
        fail(str(error))
    run_dir, config = run_directory_of(args, config)
    run = local_run_id(run_dir)
    certs = run_dir / "certs" if args.certs else None
    port = listenable(args.port, addresses[job.first_node])
    tag = attempt_tag(job)
    try:
        graph = slurm_launch(job, addresses, run, port, tag, int(config.eval_top > 0), certs,
                             **coordinator_settings(args, run_dir))  # fmt: skip
    except ValueError as error:
        fail(str(error))
    if certs is not None:
        _issue(graph, certs, args.certs)
    nodes = job_commands(graph, job, tag)
    print(f"--- job {job.id}, start {job.attempt} ({tag}):", flush=True)
    for host in graph.hosts:
        roles = ", ".join(f"{spec.count} {spec.role}" for spec in host.nodes)
        print(f"    {host.name} ({host.address}): {roles}", flush=True)
    log_dir = run_dir / "logs" / f"slurm-{job.id}-{job.attempt}"
    resume = f"`scontrol requeue {job.id}` (or the same sbatch)"
    monitor = certs / MONITOR / NODE_CONFIG if certs else None
    assert isinstance(graph.topology, PeerMesh)  # `slurm_launch`'s graph: `local_launch`'s
    return run_nodes(nodes, run, graph.topology.seed, config, run_dir, log_dir, resume, monitor,
                     requeue=lambda: _requeue(job.id, resume))  # fmt: skip


def _requeue(job: str, resume: str) -> str:
    """Put job `job` back in the queue (its time limit is near: SIGUSR1, the script's
    `--signal=B:USR1@120`), its nodes stopped: the next start resumes the run; what was done."""
    try:
        done = subprocess.run(["scontrol", "requeue", job], capture_output=True, text=True,
                              timeout=REQUEUE_S)  # fmt: skip
        why = " ".join((done.stderr or done.stdout).split()) or f"exit status {done.returncode}"
    except (OSError, subprocess.TimeoutExpired) as error:
        done, why = None, str(error)
    if done is None or done.returncode:
        return (f"time limit near: stopped; `scontrol requeue {job}` failed ({why}); {resume} "
                "resumes the run")  # fmt: skip
    return f"time limit near: stopped and requeued job {job}: its next start resumes the run"


def _issue(graph: LaunchFile, out: Path, ca_dir: Path) -> None:
    """This start's identities in `out` (those of earlier starts removed), from the CA in
    `ca_dir`."""
    if ca_dir.resolve().is_relative_to(out.resolve()):
        fail(f"--certs {ca_dir}: keep the CA outside {out}, where each start writes anew")
    try:
        ca = load_ca(ca_dir)
    except ValueError as error:
        fail(f"--certs: {error}")
    shutil.rmtree(out, ignore_errors=True)
    issue_identities(graph, out, *ca)
