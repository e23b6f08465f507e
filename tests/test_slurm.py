"""A whole run as one Slurm job (launch/slurm/derl-run.sbatch, `derl slurm`) on a real Slurm.

Checked without Slurm: the job's slots and graph (names, steps, het groups, one TLS identity per
node), and that no worker starts again once the run is over. Then a session fixture installs
Debian's Slurm (slurmctld, slurmd, munge) where it is missing and starts a cluster on this host:
munged, slurmctld and two slurmd (`slurmd -N n1`, `-N n2`, both at 127.0.0.1), each on private
ports with its key, state, spool and logs in a temporary folder; each test's jobs are cancelled
when it ends, and at the end of the session every daemon is stopped by its PID, then anything
its jobs left. It skips, saying why, only where the packages cannot be installed. On it, with a
tiny profile over loopback (multicast off, derl's default):
- a run as one job on 2 nodes exits 0, every body born once, and a job chained with
  `--dependency=afterok` runs after it; beside it on the same nodes at the same time, a
  heterogeneous job over TLS (the coordinator's component on one node, the trainers' on the
  other) runs another run to its end;
- a trainer's step cancelled mid-training is replaced by a new step; the run finishes, every
  body once;
- SIGUSR1 to the batch step mid-run (the script's --signal=B:USR1@120 before a time limit): the
  job requeues itself (`scontrol requeue`), starts again, resumes from the journal and finishes,
  every body once, both starts' logs kept;
- a run stopped before its end (SIGTERM to the batch step and every step, as at a time limit)
  exits non-zero, and the job chained after it never runs.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from cryptography.x509 import load_pem_x509_certificate
from nodes_fixtures import (
    REPO,
    assert_born_once,
    free_port,
    in_training,
    journaled,
    write_profile,
)

from derl.messages import Birth, JobLost, TrainJob
from derl.nodes.journal.segments import segments
from derl.nodes.launch.commands import NODE_CONFIG, NodeCommand
from derl.nodes.launch.identities import MONITOR, issue_identities, make_ca
from derl.nodes.launch.slurm import (
    JobGroup,
    SlurmJob,
    job_commands,
    job_from_environment,
    slurm_launch,
    tasks_per_node,
)
from derl.nodes.launch.supervisor import Supervisor
from derl.nodes.testing.processes import descendants, with_arguments
from derl.nodes.testing.waiting import wait_until

SBATCH = REPO / "launch" / "slurm" / "derl-run.sbatch"
PACKAGES = ("slurmctld", "slurmd", "slurm-client", "munge")
PROGRAMS = ("slurmctld", "slurmd", "sbatch", "munged", "mungekey")
POLICY = Path("/usr/sbin/policy-rc.d")  # dpkg asks it whether to start a service: 101 = no
NODES = ("n1", "n2")
CPUS = 4  # each node claims 4 (`SlurmdParameters=config_overrides`)
ENDED = {"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "PREEMPTED"}


# --- the graph, without Slurm ------------------------------------------------------------------


def test_tasks_per_node_and_a_jobs_slots() -> None:
    assert tasks_per_node("2(x3),1") == [2, 2, 2, 1]
    with pytest.raises(ValueError, match="SLURM_TASKS_PER_NODE"):
        tasks_per_node("2(x)")
    env = {"SLURM_JOB_ID": "42", "SLURM_JOB_NODELIST": "n[1-2]", "SLURM_TASKS_PER_NODE": "2,1",
           "SLURM_CPUS_PER_TASK": "3", "SLURM_RESTART_COUNT": "1"}  # fmt: skip
    job = job_from_environment(env, lambda nodes: ["n1", "n2"])
    assert (job.id, job.attempt, job.first_node) == ("42", 1, "n1")
    assert [(s.node, s.group, s.cpus) for s in job.slots()] == [
        ("n1", None, 3), ("n1", None, 3), ("n2", None, 3)]  # fmt: skip
    het = {"SLURM_JOB_ID": "7", "SLURM_HET_SIZE": "2", "SLURM_JOB_NODELIST_HET_GROUP_0": "a",
           "SLURM_TASKS_PER_NODE_HET_GROUP_0": "2", "SLURM_JOB_NODELIST_HET_GROUP_1": "b[1-2]",
           "SLURM_TASKS_PER_NODE_HET_GROUP_1": "4(x2)",
           "SLURM_CPUS_PER_TASK_HET_GROUP_1": "2"}  # fmt: skip
    slots = job_from_environment(het, lambda nodes: nodes.replace("[1-2]", "1 b2").split()).slots()
    assert [(s.node, s.group, s.cpus) for s in slots] == [
        ("a", 0, 1), ("a", 0, 1), *[("b1", 1, 2)] * 4, *[("b2", 1, 2)] * 4]  # fmt: skip
    with pytest.raises(ValueError, match="not in a Slurm job"):
        job_from_environment({}, lambda nodes: [])


def _job(*groups: tuple[int | None, list[str], list[int], int]) -> SlurmJob:
    return SlurmJob(id="42", groups=[JobGroup(index=i, nodes=n, tasks=t, cpus_per_task=c)
                                     for i, n, t, c in groups])  # fmt: skip


def test_the_job_graph_places_nodes_in_its_slots_as_steps(tmp_path: Path) -> None:
    """The coordinator in the batch step on the first node, the evaluator in the next slot,
    a trainer in each other, each worker an `srun --exact` step on its slot's node (its het
    group's), restarted always, listening on a free port of its node's address."""
    job = _job((0, ["a"], [2], 1), (1, ["b1", "b2"], [2, 1], 4))
    addresses = {"a": "10.0.0.1", "b1": "10.0.0.2", "b2": "10.0.0.3"}
    graph = slurm_launch(job, addresses, "r1", 5000, "j42a0xyz", 1, run_dir=tmp_path,
                         profile="demo", seed=2)  # fmt: skip
    commands = job_commands(graph, job, "j42a0xyz")
    assert [(c.name, c.role) for c in commands] == [
        ("j42a0xyz-a-coordinator-0", "coordinator"),
        ("j42a0xyz-b1-trainer-0", "trainer"),
        ("j42a0xyz-b1-trainer-1", "trainer"),
        ("j42a0xyz-b2-trainer-0", "trainer"),
        ("j42a0xyz-a-evaluator-0", "evaluator"),
    ]
    coordinator, trainer = commands[0], commands[3]
    assert coordinator.launcher == () and coordinator.args == (
        "coordinator", "--run", "r1", "--profile", "demo", "--seed", "2", "--run-dir",
        str(tmp_path), "--listen", "tcp/10.0.0.1:5000")  # fmt: skip
    assert trainer.launcher == ("srun", "--exact", "--nodes=1", "--ntasks=1", "--cpus-per-task=4",
                                "--mem=0", "--nodelist=b2", "--job-name=j42a0xyz-b2-trainer-0",
                                "--mpi=none", "--het-group=1")  # fmt: skip
    assert trainer.args == ("trainer", "--run", "r1", "--name", "j42a0xyz-b2-trainer-0",
                            "--threads", "4", "--listen", "tcp/10.0.0.3:0", "--connect",
                            "tcp/10.0.0.1:5000")  # fmt: skip
    again = trainer.argv(2)  # a restart: the same step, a new node id
    assert again[: len(trainer.launcher)] == list(trainer.launcher)
    assert again[again.index("--name") + 1] == "j42a0xyz-b2-trainer-0.r2"
    assert all(c.restart == "always" for c in commands[1:]) and commands[0].restart != "always"
    assert graph.certs is None
    small = _job((None, ["a"], [2], 1))
    plain = job_commands(slurm_launch(small, addresses, "r1", 5000, "t", 0, run_dir=tmp_path),
                         small, "t")  # fmt: skip
    assert [c.role for c in plain] == ["coordinator", "trainer"]
    assert not any(part.startswith("--het-group") for part in plain[1].launcher)
    with pytest.raises(ValueError, match="--ntasks=3 or more"):
        slurm_launch(small, addresses, "r1", 5000, "t", 1, run_dir=tmp_path)


def test_every_task_of_a_job_has_its_own_identity(tmp_path: Path) -> None:
    """With certificates: TLS endpoints, one identity per node of this start (its common name
    its node id, valid for its node's address), and a monitor's."""
    job = _job((None, ["a", "b"], [2, 2], 1))
    certs = tmp_path / "certs"
    graph = slurm_launch(job, {"a": "10.0.0.1", "b": "10.0.0.2"}, "r1", 5000, "j42a0xyz", 0,
                         certs, run_dir=tmp_path)  # fmt: skip
    (tmp_path / "ca").mkdir()
    issue_identities(graph, certs, *make_ca(tmp_path / "ca", "test CA"))
    commands = job_commands(graph, job, "j42a0xyz")
    configs = [c.args[c.args.index("--zenoh-config") + 1] for c in commands]
    assert configs == [str(certs / c.name / NODE_CONFIG) for c in commands]
    assert len(set(configs)) == 4 and all(Path(path).exists() for path in configs)
    assert all("tls/" in " ".join(c.args) and "tcp/" not in " ".join(c.args) for c in commands)
    pem = (certs / "j42a0xyz-b-trainer-1" / "node.pem").read_bytes()
    assert "CN=j42a0xyz-b-trainer-1" in load_pem_x509_certificate(pem).subject.rfc4514_string()
    assert (certs / MONITOR / NODE_CONFIG).exists() and (certs / "ca.pem").exists()


# --- a Slurm cluster on this host -------------------------------------------------------------


def _install() -> str | None:
    """Install Debian's Slurm and munge where they are missing, no service started (a
    `policy-rc.d` that says no while dpkg runs); why they cannot be, where they cannot."""
    if all(shutil.which(program) for program in PROGRAMS):
        return None
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        return "Slurm is not installed, and installing it needs root and apt-get"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    lock_path = Path(tempfile.gettempdir()) / "derl-slurm-install.lock"
    with lock_path.open("w") as lock:  # the suite's two test processes install it once
        fcntl.flock(lock, fcntl.LOCK_EX)
        if all(shutil.which(program) for program in PROGRAMS):
            return None
        ours = not POLICY.exists()
        if ours:
            POLICY.write_text("#!/bin/sh\nexit 101\n")
            POLICY.chmod(0o755)
        try:
            for argv in (["apt-get", "update", "-qq"],
                         ["apt-get", "install", "-y", "-qq", "--no-install-recommends",
                          *PACKAGES]):  # fmt: skip
                try:
                    done = subprocess.run(argv, capture_output=True, text=True, env=env,
                                          timeout=600)  # fmt: skip
                except subprocess.TimeoutExpired:
                    return f"cannot install Slurm: `{' '.join(argv)}` took over 10 minutes"
                if done.returncode:
                    said = (done.stderr or done.stdout).strip().splitlines()[-1:]
                    return f"cannot install Slurm: `{' '.join(argv)}` failed: {said}"
        finally:
            if ours:
                POLICY.unlink(missing_ok=True)
    return None


class Cluster:
    """Debian's Slurm on this host: munged, slurmctld and a slurmd per node of `NODES` (each
    `slurmd -N NAME`, all at 127.0.0.1 on ports of their own), keys, state, spool and logs in
    `root`; commands run with `env` (its SLURM_CONF, and this Python's `derl` first on PATH)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.conf = root / "slurm.conf"
        self.daemons: dict[str, subprocess.Popen] = {}
        path = f"{Path(sys.executable).parent}:{os.environ['PATH']}"
        self.env = {**os.environ, "SLURM_CONF": str(self.conf), "PATH": path}

    def start(self) -> None:
        munge = self.root / "munge"
        munge.mkdir(parents=True)
        key, sock = munge / "munge.key", munge / "socket"
        self.run("mungekey", "--create", f"--keyfile={key}")
        self._daemon("munged", "munged", "--foreground", "--force", f"--socket={sock}",
                     f"--key-file={key}", f"--log-file={munge / 'munged.log'}",
                     f"--pid-file={munge / 'munged.pid'}",
                     f"--seed-file={munge / 'seed'}")  # fmt: skip
        wait_until(lambda: self.run("munge", "-S", str(sock), "-n", check=False).returncode == 0,
                   30, "munged")  # fmt: skip
        for folder in ("state", *(f"spool/{node}" for node in NODES)):
            (self.root / folder).mkdir(parents=True)
        self.conf.write_text(self._config(sock))
        self._daemon("slurmctld", "slurmctld", "-D", "-i", "-f", str(self.conf))
        for node in NODES:
            self._daemon(f"slurmd-{node}", "slurmd", "-D", "-N", node, "-f", str(self.conf))
        wait_until(lambda: self.run("sinfo", "-h", "-o", "%t %D", check=False).stdout.strip()
                   == f"idle {len(NODES)}", 60, "both nodes idle")  # fmt: skip

    def _config(self, sock: Path) -> str:
        host, root = socket.gethostname().split(".")[0], self.root
        nodes = [f"NodeName={node} NodeHostname={host} NodeAddr=127.0.0.1 Port={free_port()} "
                 f"CPUs={CPUS} Sockets=1 CoresPerSocket={CPUS} ThreadsPerCore=1 State=UNKNOWN"
                 for node in NODES]  # fmt: skip
        return "\n".join([
            "ClusterName=derltest", f"SlurmctldHost={host}(127.0.0.1)",
            f"SlurmctldPort={free_port()}", "SlurmUser=root", "SlurmdUser=root",
            "AuthType=auth/munge", "CredType=cred/munge",
            f"AuthInfo=socket={sock},cred_expire=5",  # a requeued job starts 6 s later, not 121
            "ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none",
            "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none",
            "JobCompType=jobcomp/filetxt", f"JobCompLoc={root / 'jobs.txt'}",  # exit records
            "SelectType=select/cons_tres", "SelectTypeParameters=CR_Core", "MpiDefault=none",
            "MailProg=/bin/true", "SlurmdParameters=config_overrides", "ReturnToService=2",
            "KillWait=10",  # a pending job (requeued, heterogeneous) starts within seconds:
            "SchedulerParameters=sched_interval=2,bf_interval=1",
            f"StateSaveLocation={root / 'state'}", f"SlurmdSpoolDir={root / 'spool' / '%n'}",
            f"SlurmctldPidFile={root / 'slurmctld.pid'}", f"SlurmdPidFile={root / '%n.pid'}",
            f"SlurmctldLogFile={root / 'slurmctld.log'}", f"SlurmdLogFile={root / '%n.log'}",
            *nodes, f"PartitionName=debug Nodes={','.join(NODES)} Default=YES MaxTime=INFINITE "
            "State=UP", "",
        ])  # fmt: skip

    def _daemon(self, name: str, *argv: str) -> None:
        with (self.root / f"{name}.out").open("ab") as out:
            self.daemons[name] = subprocess.Popen(
                argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                env=self.env, start_new_session=True,
            )  # fmt: skip

    def run(self, *argv: str, check: bool = True) -> subprocess.CompletedProcess:
        done = subprocess.run(argv, capture_output=True, text=True, env=self.env, timeout=60)
        if check and done.returncode:
            raise AssertionError(f"{' '.join(argv)}: exit {done.returncode}: {done.stderr}")
        return done

    def submit(self, cwd: Path, *args: str) -> str:
        """`sbatch ARGS` in `cwd`: the job id."""
        return self.run("sbatch", "--parsable", f"--chdir={cwd}", *args).stdout.strip()

    def job(self, job: str) -> dict[str, str]:
        """`scontrol show job`'s fields of `job` (its first component's)."""
        line = self.run("scontrol", "show", "job", "--oneliner", job).stdout.splitlines()[0]
        return dict(re.findall(r"(\w+)=(\S*)", line))

    def ended(self, job: str, timeout: float, restarts: int = 0) -> dict[str, str]:
        """`job`'s fields once it ended after `restarts` requeues."""
        return wait_until(  # type: ignore[return-value]
            lambda: (fields := self.job(job))["JobState"] in ENDED
            and int(fields["Restarts"]) >= restarts and fields,
            timeout, f"job {job} to end",
        )  # fmt: skip

    def steps(self, job: str) -> dict[str, str]:
        """The running steps of `job` by name: their ids (JOB.STEP)."""
        lines = self.run("squeue", "-h", "-s", "-j", job, "-o", "%i %j").stdout.splitlines()
        return {name: step for step, name in (line.split() for line in lines)}

    def clear(self) -> None:
        """Cancel every job and wait until they are gone."""
        self.run("scancel", f"--user={os.getuid()}")
        wait_until(lambda: not self.run("squeue", "-h").stdout.strip(), 60, "the jobs to end")

    def stop(self) -> None:
        """Cancel every job, stop the daemons by PID, then whatever the jobs left."""
        with contextlib.suppress(Exception):
            self.clear()
        for process in reversed(self.daemons.values()):
            process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        marker = f"SLURM_CONF={self.conf}".encode()
        for pid in _processes_with(marker):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def _processes_with(variable: bytes) -> list[int]:
    """The processes whose environment holds `variable` (NAME=VALUE), other than this one."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and int(entry.name) != os.getpid():
            with contextlib.suppress(OSError):
                if variable in (entry / "environ").read_bytes().split(b"\0"):
                    found.append(int(entry.name))
    return found


@pytest.fixture
def slurm(slurm_cluster: Cluster) -> Iterator[Cluster]:
    """The session's Slurm cluster, its jobs cancelled when the test ends."""
    try:
        yield slurm_cluster
    finally:
        slurm_cluster.clear()


@pytest.fixture(scope="session")
def slurm_cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """A Slurm cluster of two nodes on this host for the session (set-up printed)."""
    started = time.monotonic()
    reason = _install()
    if reason is not None:
        pytest.skip(reason)
    installed = time.monotonic()
    cluster = Cluster(tmp_path_factory.mktemp("slurm"))
    try:
        cluster.start()
        print(f"Slurm: installed in {installed - started:.1f} s, cluster up "
              f"{time.monotonic() - installed:.1f} s later")  # fmt: skip
        yield cluster
    finally:
        cluster.stop()


# --- runs as Slurm jobs -----------------------------------------------------------------------


def _told(slurm: Cluster, folder: Path, job: str) -> str:
    """What a test that failed shows: the job's output, its nodes' logs and its exit record."""
    parts = [f"== job {job}: {slurm.job(job)}"]
    for path in [*folder.glob(f"derl-run-{job}.out"), *sorted(folder.glob("run/logs/*/*.log"))]:
        parts.append(f"== {path.relative_to(folder)}\n{path.read_text(errors='replace')[-3000:]}")
    return "\n".join(parts)


def _sbatch_run(
    slurm: Cluster, folder: Path, *options: str, certs: Path | None = None, **profile: object
) -> str:
    """A derl-run.sbatch job of `options` on a tiny profile (TINY_PROFILE changed by `profile`)
    in `folder`, its run directory `folder`/run, TLS with the CA in `certs`: the job id."""
    path = write_profile(folder / "profile.yaml", **profile)
    tls = ("--certs", str(certs)) if certs else ()
    return slurm.submit(folder, *options, str(SBATCH), "--profile", str(path), "--run-dir", "run",
                        *tls)  # fmt: skip


@pytest.mark.slow
def test_a_run_is_one_job_on_two_nodes(slurm: Cluster, tmp_path: Path) -> None:
    """Exit 0, every body born once, trainers as steps on both nodes under this start's names,
    and a job chained with afterok runs once it is done. Beside it on the same nodes at the same
    time, another run as a heterogeneous job over TLS: its coordinator's component on n1, its
    trainers' on n2 (`--het-group=1`), every node with its own identity from the user's CA."""
    beside = tmp_path / "beside"
    beside.mkdir()
    slurm.run(sys.executable, "-m", "derl.nodes.cli", "certs", "--out", str(beside / "ca"))
    job = _sbatch_run(slurm, tmp_path, "--nodes=2", "--ntasks=3")
    het = _sbatch_run(slurm, beside, "--nodelist=n1", "--ntasks=1", ":", "--nodelist=n2",
                      "--ntasks=2", certs=beside / "ca")  # fmt: skip
    chained = slurm.submit(tmp_path, f"--dependency=afterok:{job}", "--output=chained.out",
                           "--wrap", "ls run/summary.json")  # fmt: skip
    records = [slurm.ended(j, timeout=240) for j in (job, het)]
    for record, folder, j in zip(records, (tmp_path, beside), (job, het), strict=True):
        told = _told(slurm, folder, j)
        assert (record["JobState"], record["ExitCode"]) == ("COMPLETED", "0:0"), told
        assert_born_once(folder / "run", 3)
    assert records[1]["StartTime"] < records[0]["EndTime"]  # side by side on n1 and n2
    out = (tmp_path / f"derl-run-{job}.out").read_text()
    assert "done: 3 bodies" in out and "fingerprint" in out, out
    logs = sorted(p.stem for p in (tmp_path / "run" / "logs" / f"slurm-{job}-0").glob("*.log"))
    assert len(logs) == 3 and all(name.startswith(f"j{job}a0") for name in logs), logs
    assert {name.split("-")[1] for name in logs if "-trainer-" in name} == {"n1", "n2"}, logs
    assert slurm.ended(chained, timeout=60)["JobState"] == "COMPLETED"
    assert (tmp_path / "chained.out").read_text().strip() == "run/summary.json"
    trainers = sorted((beside / "run" / "logs" / f"slurm-{het}-0").glob("*-trainer-*.log"))
    assert [log.stem.split("-")[1] for log in trainers] == ["n2", "n2"], _told(slurm, beside, het)
    for log in trainers:
        text = log.read_text()
        assert "--het-group=1" in text and "--connect tls/127.0.0.1:" in text, text
        assert f"--zenoh-config run/certs/{log.stem}/zenoh.json5" in text, text


SLOWER = {"train_steps": 40960}  # trainings of ~2 s (on a quiet core): something to cut mid-way


@pytest.mark.slow
def test_a_cancelled_trainer_step_is_replaced(slurm: Cluster, tmp_path: Path) -> None:
    job = _sbatch_run(slurm, tmp_path, "--nodes=2", "--ntasks=3", **SLOWER)
    run_dir = tmp_path / "run"
    first = wait_until(lambda: in_training(run_dir), 120, "a job in training")[0]
    named = with_arguments("--name", first.node)  # its srun step and the trainer that step runs
    for pid in set(named) - {p for p in named if set(descendants(p)) & set(named)}:
        os.kill(pid, signal.SIGSTOP)  # the trainer frozen mid-job at once, on any machine
    step = wait_until(lambda: slurm.steps(job).get(first.node), 30, f"{first.node}'s step")
    slurm.run("scancel", step)
    record = slurm.ended(job, timeout=180)
    told = _told(slurm, tmp_path, job)
    assert (record["JobState"], record["ExitCode"]) == ("COMPLETED", "0:0"), told
    assert_born_once(run_dir, 3)
    assert any(m.node == first.node for m in journaled(run_dir, JobLost)), told  # mid-training
    log = (run_dir / "logs" / f"slurm-{job}-0" / f"{first.node}.log").read_text()
    assert f"--name {first.node}.r1 " in log and f"trainer {first.node}.r1 ready" in log, told


@pytest.mark.slow
def test_a_job_near_its_time_limit_requeues_itself_and_resumes_the_run(
    slurm: Cluster, tmp_path: Path
) -> None:
    """SIGUSR1 to the batch step (what the script's --signal=B:USR1@120 makes Slurm send before
    the time limit): `derl slurm` stops its nodes and requeues the job, which starts again
    (SLURM_RESTART_COUNT 1) on the same run directory: the run resumes from its journal (a second
    segment), every body is born once (the first start's trainings in flight are taken back after
    their lease), and both starts' logs are kept."""
    job = _sbatch_run(slurm, tmp_path, "--nodes=2", "--ntasks=3", lease_s=10.0, **SLOWER)
    run_dir = tmp_path / "run"
    wait_until(lambda: journaled(run_dir, Birth), 120, "a birth")
    slurm.run("scancel", "--batch", "--signal=USR1", job)
    record = slurm.ended(job, timeout=240, restarts=1)
    told = _told(slurm, tmp_path, job)
    assert (record["JobState"], record["ExitCode"], record["Restarts"]) == (
        "COMPLETED", "0:0", "1"), told  # fmt: skip
    assert_born_once(run_dir, 3)
    assert len(segments(run_dir)) == 2, told
    out = (tmp_path / f"derl-run-{job}.out").read_text()
    assert f"--- job {job}, start 0" in out and f"--- job {job}, start 1" in out, told
    assert f"time limit near: stopped and requeued job {job}" in out, told
    for start in (0, 1):
        logs = {p.stem for p in (run_dir / "logs" / f"slurm-{job}-{start}").glob("*.log")}
        assert len(logs) == 3 and all(name.startswith(f"j{job}a{start}") for name in logs)


@pytest.mark.slow
def test_a_run_stopped_before_its_end_fails_its_job(slurm: Cluster, tmp_path: Path) -> None:
    """SIGTERM to the batch step and every step (what a time limit does first): the run stops
    unfinished, the job fails, and a job chained after it with afterok never runs."""
    job = _sbatch_run(slurm, tmp_path, "--nodes=2", "--ntasks=3", total=40, train_steps=40960)
    chained = slurm.submit(tmp_path, f"--dependency=afterok:{job}", "--wrap", "true")
    wait_until(lambda: journaled(tmp_path / "run", TrainJob), 120, "a training")
    slurm.run("scancel", "--full", "--signal=TERM", job)
    record = slurm.ended(job, timeout=60)
    told = _told(slurm, tmp_path, job)
    assert (record["JobState"], record["ExitCode"]) == ("FAILED", "130:0"), told
    assert "resumes the run" in (tmp_path / f"derl-run-{job}.out").read_text(), told
    never = wait_until(lambda: slurm.job(chained)["Reason"] == "DependencyNeverSatisfied", 30,
                       "the chained job's dependency to fail")  # fmt: skip
    assert never and slurm.job(chained)["JobState"] == "PENDING"


def test_no_worker_starts_again_once_the_run_is_over(tmp_path: Path) -> None:
    """Workers restart `always` under Slurm (one stopped by a signal exits 0), but once the run
    is over they end by themselves before the coordinator does: none is started again."""
    ends = NodeCommand(host="h", name="t", role="trainer", args=(), launcher=("true",),
                       restart="always", max_restarts=5)  # fmt: skip
    lasts = NodeCommand(host="h", name="c", role="coordinator", args=(),
                        launcher=("sh", "-c", "sleep 60"))  # fmt: skip
    for over, restarted in ((False, True), (True, False)):
        supervisor = Supervisor([lasts, ends], tmp_path / str(over))
        if over:
            supervisor.over.set()
        runs = threading.Thread(target=supervisor.run, kwargs={"poll_s": 0.05})
        runs.start()
        worker = supervisor.slots[1]
        wait_until(lambda: worker.restarts if restarted else worker.finished, 30, "the worker")  # noqa: B023
        supervisor.stop.set()
        runs.join(30)
        assert (worker.restarts > 0, worker.finished) == (restarted, not restarted)
