"""Launch files: validation, the exact commands `derl launch` builds (dry run), and real
launches on loopback: a run to the end with a killed trainer restarted by its policy, and SIGTERM
stopping every node. (The Slurm job: tests/test_slurm.py.)"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
from pathlib import Path

import pytest
import yaml
from nodes_fixtures import (
    REPO,
    Processes,
    assert_born_once,
    derl_argv,
    free_port,
    jobs,
    pid_alive,
    run_id,
    write_profile,
)
from pydantic import ValidationError

from derl.evolution import load_profile
from derl.nodes.cli.main import build_parser
from derl.nodes.launch.commands import build_commands, dry_run_text, plan
from derl.nodes.launch.local import LOCAL_FILE, local_launch
from derl.nodes.launch.model import LaunchFile, NodeSpec, load
from derl.nodes.testing.waiting import wait_until

LOCAL = REPO / "launch" / "local.yaml"
CLUSTER = REPO / "launch" / "cluster.example.yaml"


def _derl(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run(derl_argv(*args), capture_output=True, text=True, cwd=cwd, timeout=60)


def _parses(line: str) -> None:
    """A printed `derl ...` line is accepted by the real command line."""
    argv = shlex.split(line)
    assert Path(argv[0]).name == "derl", line
    args = build_parser().parse_args(argv[1:])
    assert callable(args.handler)


def _mesh(tmp: Path, **host: object) -> dict:
    return {
        "run": "r1",
        "run_dir": str(tmp / "run"),
        "profile": "smoke",
        "topology": {"kind": "peer_mesh", "seed": "tcp/10.1.0.1:7447"},
        "hosts": [
            {"name": "head", "address": "10.1.0.1", "listen": "tcp/10.1.0.1:7447",
             "nodes": [{"role": "coordinator"}, {"role": "trainer", "count": 2}]},
            {"name": "a", "address": "10.1.0.2", "listen": "tcp/10.1.0.2:7500",
             "nodes": [{"role": "trainer", "count": 3, "threads": 2}], **host},
        ],
    }  # fmt: skip


# --- the shipped files ---------------------------------------------------------------------


def test_local_launch_file_dry_run(tmp_path: Path) -> None:
    result = _derl("launch", str(LOCAL), "--dry-run", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stdout.splitlines() if not line.startswith("#")]
    assert lines == [
        "derl coordinator --run local-smoke --profile smoke --run-dir runs/local-smoke "
        "--listen tcp/127.0.0.1:7447",
        "derl trainer --run local-smoke --name local-trainer-0 --threads 1 "
        "--listen tcp/127.0.0.1:0 --connect tcp/127.0.0.1:7447",
        "derl trainer --run local-smoke --name local-trainer-1 --threads 1 "
        "--listen tcp/127.0.0.1:0 --connect tcp/127.0.0.1:7447",
        "derl evaluator --run local-smoke --name local-evaluator-0 --threads 1 "
        "--listen tcp/127.0.0.1:0 --connect tcp/127.0.0.1:7447",
    ]
    for line in lines:
        _parses(line)
    assert not list(tmp_path.iterdir())  # a dry run starts and writes nothing


def test_derl_run_starts_the_local_launch_files_graph_with_its_numbers(tmp_path: Path) -> None:
    """`derl run` and `derl study` start the nodes launch/local.yaml declares (one declaration,
    packaged with derl), with the run's id, directory, profile, port and worker counts."""
    assert LOCAL.resolve() == LOCAL_FILE.resolve()
    declared = {spec.role: spec for spec in load(LOCAL).hosts[0].nodes}
    endpoint = "tcp/127.0.0.1:9000"
    run = local_launch("r1", endpoint, {"trainer": 3, "evaluator": 1}, run_dir=tmp_path,
                       profile="demo", seed=2)  # fmt: skip
    commands = build_commands(run)
    assert [c.name for c in commands] == [
        "local-coordinator-0",
        *(f"local-trainer-{k}" for k in range(3)),
        "local-evaluator-0",
    ]
    assert commands[0].args == ("coordinator", "--run", "r1", "--profile", "demo", "--seed", "2",
                                "--run-dir", str(tmp_path), "--listen", endpoint)  # fmt: skip
    assert all(c.args[-2:] == ("--connect", endpoint) for c in commands[1:])
    assert all(c.max_restarts == declared[c.role].max_restarts for c in commands)
    no_evaluator = local_launch("r1", endpoint, {"trainer": 1, "evaluator": 0}, run_dir=tmp_path)
    assert [c.role for c in build_commands(no_evaluator)] == ["coordinator", "trainer"]
    study = build_commands(local_launch("s1", endpoint, {"evaluator": 2}, study=tmp_path))
    assert [c.role for c in study] == ["coordinator", "evaluator", "evaluator"]
    assert study[0].args == ("coordinator", "--run", "s1", "--study", str(tmp_path), "--listen",
                             endpoint)  # fmt: skip
    board = build_commands(local_launch("r1", endpoint, {"trainer": 2, "evaluator": 1},
                                        tmp_path / "tb", run_dir=tmp_path))  # fmt: skip
    written = [c.role for c in board if "--tensorboard" in c.args]
    assert written == ["trainer", "trainer"]  # each training from its trainer: the trainers'
    assert board[1].args[board[1].args.index("--tensorboard") + 1] == str(tmp_path / "tb")


def test_only_trainers_take_a_tensorboard_folder_in_a_launch_file() -> None:
    trainer = NodeSpec(role="trainer", tensorboard=Path("tb"))
    assert trainer.tensorboard == Path("tb")
    with pytest.raises(ValidationError, match=r"trainer's setting \(evaluator nodes train"):
        NodeSpec(role="evaluator", tensorboard=Path("tb"))


def test_cluster_example_dry_run_starts_ssh_hosts_over_ssh() -> None:
    result = _derl("launch", str(CLUSTER.relative_to(REPO)), "--dry-run")
    assert result.returncode == 0, result.stderr
    out = result.stdout.splitlines()
    ssh = [line for line in out if line.startswith("ssh ")]
    assert [shlex.split(line)[4] for line in ssh] == [
        "10.0.0.2",
        "derl@10.0.0.11",
        "derl@10.0.0.12",
    ]
    for line, host in zip(ssh, ("router", "gpu1", "gpu2"), strict=True):
        argv = shlex.split(line)
        assert argv[:4] == ["ssh", "-tt", "-o", "BatchMode=yes"]
        assert argv[5] == (
            "cd /srv/derl && exec /srv/derl/.venv/bin/derl launch launch/cluster.example.yaml "
            f"--host {host}"
        )
    assert out[0] == "# host router: over ssh (10.0.0.2)"  # the router starts first
    local = [line for line in out if line.startswith("derl ")]
    assert local == [
        "derl coordinator --run paper-ft-1 --profile paper --env ft --run-dir runs/paper-ft-1 "
        "--mode client --connect tcp/10.0.0.2:7447"
    ]
    there = [line.removeprefix("#   there: ") for line in out if line.startswith("#   there: ")]
    assert there[0] == "/srv/derl/.venv/bin/derl router --listen tcp/0.0.0.0:7447"
    trainers = [line for line in there if " trainer " in line]
    assert len(trainers) == 72 and len({shlex.split(t)[5] for t in trainers}) == 72  # unique names
    assert all(
        t.endswith("--threads 2 --mode client --connect tcp/10.0.0.2:7447") for t in trainers
    )
    assert sum(" evaluator " in line for line in there) == 2
    for line in [*local, *there]:
        _parses(line.replace("/srv/derl/.venv/bin/derl", "derl"))


def test_a_host_started_by_name_runs_its_nodes_here() -> None:
    launch = load(CLUSTER)
    commands = plan(launch, CLUSTER, ["gpu2"])
    assert {c.host for c in commands} == {"gpu2"} and all(c.remote is None for c in commands)
    assert [c.role for c in commands] == ["trainer"] * 36 + ["evaluator"] * 2
    assert commands[0].argv()[0] == "/srv/derl/.venv/bin/derl"
    no_ssh = plan(launch, CLUSTER, ssh=False)
    assert [c.host for c in no_ssh] == ["head"]
    with pytest.raises(KeyError, match="no host 'gpu9'"):
        plan(launch, CLUSTER, ["gpu9"])
    result = _derl("launch", str(CLUSTER), "--host", "gpu9", "--dry-run")
    assert result.returncode != 0 and "no host 'gpu9'" in result.stderr


# --- commands --------------------------------------------------------------------------------


def test_peer_mesh_ports_seed_and_zenoh_config(tmp_path: Path) -> None:
    data = _mesh(tmp_path, zenoh_config="certs-a/zenoh.json5")
    data["zenoh_config"] = "conf/zenoh.json5"
    launch = LaunchFile.model_validate(data)
    by_name = {c.name: c.derl_args() for c in build_commands(launch)}
    head = by_name["head-coordinator-0"]
    assert "--connect" not in head  # the coordinator is the seed
    assert head[head.index("--listen") + 1] == "tcp/10.1.0.1:7447"
    assert head[head.index("--zenoh-config") + 1] == "conf/zenoh.json5"
    assert by_name["head-trainer-1"][-6:] == [
        "--listen", "tcp/10.1.0.1:7449", "--connect", "tcp/10.1.0.1:7447",
        "--zenoh-config", "conf/zenoh.json5",
    ]  # fmt: skip
    a2 = by_name["a-trainer-2"]
    assert a2[a2.index("--listen") + 1] == "tcp/10.1.0.2:7502"
    assert a2[a2.index("--threads") + 1] == "2"
    assert a2[a2.index("--zenoh-config") + 1] == "certs-a/zenoh.json5"  # the host's own config
    zero = LaunchFile.model_validate(_mesh(tmp_path, listen="tls/10.1.0.2:0"))
    listens = {c.derl_args()[c.derl_args().index("--listen") + 1]
               for c in build_commands(zero, ["a"])}  # fmt: skip
    assert listens == {"tls/10.1.0.2:0"}


def test_a_launch_files_seed_reaches_the_coordinator(tmp_path: Path) -> None:
    launch = LaunchFile.model_validate({**_mesh(tmp_path), "seed": 3})
    head = next(c for c in build_commands(launch) if c.role == "coordinator").derl_args()
    assert head[head.index("--seed") + 1] == "3"
    assert build_parser().parse_args(head).seed == 3
    unseeded = next(c for c in build_commands(LaunchFile.model_validate(_mesh(tmp_path))))
    assert "--seed" not in unseeded.derl_args()


def test_a_launch_file_can_run_a_study_with_evaluators(tmp_path: Path) -> None:
    """`study: DIR` instead of `run_dir`: the coordinator coordinates the study (`derl study
    --plan-only` wrote it); trainers are refused, and so is a file with neither or both."""
    data = _mesh(tmp_path)
    del data["run_dir"]
    for host in data["hosts"]:
        host["nodes"] = [n if n["role"] == "coordinator" else {**n, "role": "evaluator"}
                         for n in host["nodes"]]  # fmt: skip
    study = LaunchFile.model_validate({**data, "study": str(tmp_path / "study")})
    head = next(c for c in build_commands(study) if c.role == "coordinator").derl_args()
    assert head[head.index("--study") + 1] == str(tmp_path / "study") and "--profile" not in head
    assert build_parser().parse_args(head).study == tmp_path / "study"
    assert study.directory == tmp_path / "study"
    planned_here = LaunchFile.model_validate(
        {**data, "study": "s", "study_runs": ["runs/ft-s1", "runs/vt-s1"], "profile": "paper"}
    )
    head = next(c for c in build_commands(planned_here) if c.role == "coordinator").derl_args()
    parsed = build_parser().parse_args(head)
    assert parsed.study_runs == [Path("runs/ft-s1"), Path("runs/vt-s1")]
    assert parsed.profile == "paper" and parsed.listen  # the bus flags still follow
    with pytest.raises(ValueError, match="go with `study`"):
        LaunchFile.model_validate({**_mesh(tmp_path), "study_runs": ["r"]})
    with pytest.raises(ValueError, match="one of them"):
        LaunchFile.model_validate(data)
    with pytest.raises(ValueError, match="one of them"):
        LaunchFile.model_validate({**_mesh(tmp_path), "study": "s"})
    with pytest.raises(ValueError, match="evaluator nodes, not trainers"):
        LaunchFile.model_validate({**_mesh(tmp_path), "run_dir": None, "study": "s"})


def test_a_run_directory_refuses_another_seed(tmp_path: Path) -> None:
    """Resuming a run with another --seed would mix two replicates in one journal."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "profile.json").write_text(load_profile("smoke", seed=0).model_dump_json())
    port = free_port()
    result = _derl("coordinator", "--run", "r", "--profile", "smoke", "--seed", "1",
                   "--run-dir", str(run_dir), "--listen", f"tcp/127.0.0.1:{port}")  # fmt: skip
    assert result.returncode != 0
    assert "with seed 0, not smoke in ft with seed 1" in result.stderr
    assert not list((run_dir).glob("*.mcap"))


def test_wildcard_listen_on_the_seed_host_is_the_seed(tmp_path: Path) -> None:
    data = _mesh(tmp_path)
    data["hosts"][0]["listen"] = "tcp/0.0.0.0:7447"
    commands = {c.name: c.derl_args() for c in build_commands(LaunchFile.model_validate(data))}
    assert "--connect" not in commands["head-coordinator-0"]
    assert "--connect" in commands["head-trainer-0"]


def test_a_node_entry_can_say_where_its_processes_listen(tmp_path: Path) -> None:
    """A node entry's `listen` wins over its host's (process k of the entry on port + k); in a
    router topology nodes are clients, and the key is refused."""
    data = _mesh(tmp_path)
    data["hosts"][1]["nodes"][0]["listen"] = "tcp/10.1.0.2:8000"
    commands = {c.name: c.derl_args() for c in build_commands(LaunchFile.model_validate(data))}
    listens = [commands[f"a-trainer-{k}"][commands[f"a-trainer-{k}"].index("--listen") + 1]
               for k in range(3)]  # fmt: skip
    assert listens == ["tcp/10.1.0.2:8000", "tcp/10.1.0.2:8001", "tcp/10.1.0.2:8002"]
    router = {"kind": "router", "endpoint": "tcp/10.1.0.1:7447", "host": "head"}
    data["hosts"][0]["nodes"].append({"role": "router"})
    with pytest.raises(ValueError, match="`listen` is for a peer mesh"):
        LaunchFile.model_validate({**data, "topology": router})


def test_restarted_worker_gets_a_new_node_id(tmp_path: Path) -> None:
    commands = build_commands(LaunchFile.model_validate(_mesh(tmp_path)), ["a"])
    assert "a-trainer-0" in commands[0].derl_args(0)
    assert "a-trainer-0.r2" in commands[0].derl_args(2)
    coordinator = build_commands(LaunchFile.model_validate(_mesh(tmp_path)), ["head"])[0]
    assert coordinator.derl_args(3) == coordinator.derl_args(0)  # resumes its journal


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d.update(bogus=1), "Extra inputs are not permitted"),
        (lambda d: d["hosts"][0]["nodes"][0].update(restart="sometimes"), "restart"),
        (lambda d: d["hosts"][1]["nodes"].append({"role": "coordinator"}), "one coordinator"),
        (lambda d: d["hosts"][0]["nodes"].pop(0), "exactly one coordinator"),
        (lambda d: d["hosts"][1].update(name="head"), "host names must be unique"),
        (lambda d: d["hosts"][1].pop("listen"), "needs a `listen` endpoint"),
        (lambda d: d["topology"].update(seed="10.1.0.1:7447"), "not a Zenoh endpoint"),
        (lambda d: d["hosts"][0].update(listen="tcp/10.1.0.1:7500"), "no node listens on the seed"),
        (lambda d: d["hosts"][0]["nodes"].append({"role": "router"}), "need `topology: {kind"),
        (lambda d: d.update(topology={"kind": "router", "endpoint": "tcp/10.1.0.9:7447",
                                      "host": "head"}), "needs one node `role: router`"),
        (lambda d: d.update(topology={"kind": "router", "endpoint": "tcp/10.1.0.9:7447",
                                      "host": "nowhere"}), "not among the hosts"),
        (lambda d: d.update(run="has space"), "run"),
        (lambda d: d["hosts"][0]["nodes"][1].update(count=0), "count"),
    ],
)  # fmt: skip
def test_invalid_launch_files_are_rejected(tmp_path: Path, change, message: str) -> None:
    data = _mesh(tmp_path)
    change(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match=re.escape(message)):
        load(path)


def test_invalid_file_is_an_error_on_the_command_line(tmp_path: Path) -> None:
    data = _mesh(tmp_path)
    data["hosts"][1]["nodes"].append({"role": "coordinator"})
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    result = _derl("launch", str(path), "--dry-run")
    assert result.returncode != 0
    assert "not a valid launch file" in result.stderr and "exactly one coordinator" in result.stderr


def test_router_topology_commands(tmp_path: Path) -> None:
    data = _mesh(tmp_path)
    data["topology"] = {"kind": "router", "endpoint": "tls/10.1.0.9:7447", "host": "hub"}
    data["hosts"].append({"name": "hub", "address": "10.1.0.9", "nodes": [{"role": "router"}]})
    commands = build_commands(LaunchFile.model_validate(data))
    assert commands[0].derl_args() == ["router", "--listen", "tls/10.1.0.9:7447"]
    for command in commands[1:]:
        assert command.derl_args()[-4:] == ["--mode", "client", "--connect", "tls/10.1.0.9:7447"]
    text = dry_run_text(plan(LaunchFile.model_validate(data), Path("f.yaml"), ["hub", "a"]))
    assert text.splitlines()[:2] == ["# host hub: on this host",
                                     "derl router --listen tls/10.1.0.9:7447"]  # fmt: skip


def test_default_hosts_are_this_machine_or_those_without_ssh(tmp_path: Path) -> None:
    data = _mesh(tmp_path)
    data["hosts"][1]["ssh"] = "me@10.1.0.2"
    launch = LaunchFile.model_validate(data)
    commands = plan(launch, Path("x.yaml"))
    assert [(c.host, c.role) for c in commands][:3] == [
        ("head", "coordinator"), ("head", "trainer"), ("head", "trainer")]  # fmt: skip
    assert commands[-1].argv()[:5] == ["ssh", "-tt", "-o", "BatchMode=yes", "me@10.1.0.2"]
    assert commands[-1].argv()[5].endswith("launch x.yaml --host a")
    data["hosts"].append({"name": "local", "nodes": [{"role": "trainer"}]})
    only_local = plan(LaunchFile.model_validate(data), Path("x.yaml"), ssh=False)
    assert {c.host for c in only_local} == {"local"}  # the host named `local` is this machine


# --- real launches -------------------------------------------------------------------------


def _local_launch(tmp: Path, trainers: int, total: int, **profile: object) -> tuple[Path, Path]:
    port = free_port(span=1 + trainers)
    run_dir = tmp / "run"
    launch = {
        "run": run_id(),
        "run_dir": str(run_dir),
        "profile": str(write_profile(tmp / "profile.yaml", total=total, **profile)),
        "topology": {"kind": "peer_mesh", "seed": f"tcp/127.0.0.1:{port}"},
        "hosts": [{"name": "local", "listen": f"tcp/127.0.0.1:{port}", "nodes": [
            {"role": "coordinator", "restart": "never"},
            {"role": "trainer", "count": trainers, "restart": "on-failure", "max_restarts": 2},
        ]}],
    }  # fmt: skip
    path = tmp / "launch.yaml"
    path.write_text(yaml.safe_dump(launch))
    return path, run_dir


def _pids(launcher_log: str) -> dict[str, list[int]]:
    started: dict[str, list[int]] = {}
    for name, pid in re.findall(r"(\S+) started \(pid (\d+)\)", launcher_log):
        started.setdefault(name, []).append(int(pid))
    return started


@pytest.mark.slow
def test_launch_runs_to_the_end_and_restarts_a_killed_trainer(tmp_path: Path) -> None:
    # Trainings of ~1 s (8 PPO iterations), so the run is still going when a trainer dies: with
    # the tiny profile's 0.3 s ones, one trainer could take all three bodies before the other
    # was ready, and the run could end before the kill. The victim is whichever trainer got the
    # first job.
    path, run_dir = _local_launch(tmp_path, trainers=2, total=3, train_steps=16384)
    processes = Processes(tmp_path / "test-logs")
    try:
        launcher = processes.start("launcher", derl_argv("launch", str(path)))
        first = wait_until(lambda: jobs(run_dir), 90, "the first job")[0].node
        victim = _pids(processes.log("launcher"))[first][0]
        os.killpg(victim, signal.SIGKILL)
        wait_until(lambda: f"{first} exited with -9: restart 1/2" in processes.log("launcher"),
                   10, "the launcher noticing the kill")  # fmt: skip
        wait_until(lambda: launcher.poll() is not None, 150, "the launcher to finish the run")
        log = processes.log("launcher")
        assert launcher.returncode == 0, log
        assert "the coordinator finished the run" in log
        assert len(_pids(log)[first]) == 2  # started again
        assert_born_once(run_dir, 3)
        node_log = (run_dir / "logs" / f"{first}.log").read_text()
        assert f"--name {first}.r1" in node_log  # the restart has a new node id
        assert {p.name for p in (run_dir / "logs").iterdir()} == {
            "local-coordinator-0.log", "local-trainer-0.log", "local-trainer-1.log"}  # fmt: skip
        assert not [pid for pids in _pids(log).values() for pid in pids if pid_alive(pid)]
    finally:
        processes.close()


@pytest.mark.slow
def test_sigterm_stops_every_node(tmp_path: Path) -> None:
    path, run_dir = _local_launch(tmp_path, trainers=1, total=40)
    processes = Processes(tmp_path / "test-logs")
    try:
        launcher = processes.start("launcher", derl_argv("launch", str(path)))
        wait_until(lambda: jobs(run_dir), 90, "the first job")
        pids = [pid for ps in _pids(processes.log("launcher")).values() for pid in ps]
        assert len(pids) == 2 and all(pid_alive(pid) for pid in pids)
        launcher.send_signal(signal.SIGTERM)
        assert launcher.wait(timeout=20) == 130
        assert not [pid for pid in pids if pid_alive(pid)]
    finally:
        processes.close()
