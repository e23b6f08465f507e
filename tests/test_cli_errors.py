"""Bad input on the command line gets one clear line and a non-zero exit, never a traceback or a
hang: one row per mistake a user makes (a budget below one rollout, an impossible genome, zero
workers or copies, a port in use, a missing run directory or log, a run directory that is a
file, a misspelt key in a profile or a launch file, a profile file that is empty or starts from
no built-in profile, a tournament larger than the population, a job's own setting among a
profile's PPO hyperparameters, a misspelt key or a wrong value in --set or one breaking a rule
between settings, a misspelt profile name, a missing genome or folder to resume, another value
of a setting of a run begun (or fewer bodies to --extend it to), a training's folder as a run's,
an unknown message type, a folder with no trained body, a study with no runs, of a missing run
or not made yet, a run directory of another run id, a monitor or a topic that hears nothing (the
line says how it joined the bus: by default the local run's endpoint, $DERL_LOCAL_PORT here) or is
asked to listen a negative time, a report of a file that is no log, an export with nothing to
write, a missing or misspelt Zenoh config, an argument no option takes; a training's folder that
is a file or cannot be made, a resume with a new training's flags or of no stopped training, a
report, an export or bodies into a folder that cannot be made, a video of a format derl does
not write, in no folder or where no file can be made (said before the episode is filmed), an
endpoint without a port or with one out of range). A mistake in a command's own flags (--set
included) exits 2, as argparse's do."""

from __future__ import annotations

import json
import os
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from nodes_fixtures import derl_argv, free_port

from derl.evolution import load_profile
from derl.messages import WorkerReady
from derl.nodes.cli.main import main
from derl.nodes.cli.run import listenable
from derl.nodes.journal.segments import Journal
from derl.nodes.runtime.ports import bindable, ephemeral_range
from derl.unimal import Genome

GENOME = "genome.json"


@pytest.fixture
def busy_port() -> Iterator[int]:
    """A port something already listens on."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", free_port()))
        taken.listen()
        yield taken.getsockname()[1]


@pytest.fixture(scope="module")
def trained() -> dict[str, bytes]:
    """The files of a finished `derl train` folder (a body trained one short iteration)."""
    from derl.lifetime import learn, ppo_config
    from derl.unimal import sample_population

    (genome,) = sample_population(1, np.random.default_rng(0))
    _, result = learn(genome, "ft", ppo_config("ft", 1024, seed=0, num_envs=8))
    return {"genome.json": genome.model_dump_json().encode(),
            "checkpoint.pt": result.checkpoint.to_bytes(),
            "result.json": json.dumps({"task": "ft", "config": {}}).encode()}  # fmt: skip


def _files(tmp: Path, genome: Genome, trained: dict[str, bytes]) -> None:
    (tmp / GENOME).write_text(genome.model_dump_json())
    (tmp / "trained").mkdir()
    for name, data in trained.items():
        (tmp / "trained" / name).write_bytes(data)
    (tmp / "typo.yaml").write_text(yaml.safe_dump({"profile": "smoke", "populaton": 3}))
    # a job's own setting under `ppo`: each job's copies come from the profile's `num_envs`
    (tmp / "job-key.yaml").write_text(yaml.safe_dump({"profile": "smoke", "ppo": {"num_envs": 64}}))
    launch = {"run": "r", "run_dir": "runs/r", "topology": {"kind": "peer_mesh",
              "seed": "tcp/127.0.0.1:7447"}, "hosts": [{"name": "h", "nodes": [{"role":
              "trainer", "cont": 2}]}]}  # fmt: skip
    (tmp / "launch.yaml").write_text(yaml.safe_dump(launch))
    (tmp / "a-file").write_text("")
    (tmp / "smok.yaml").write_text("profile: smok\n")  # a misspelt built-in profile
    (tmp / "empty.yaml").write_text("# nothing set yet\n")
    (tmp / "big-tournament.yaml").write_text("profile: smoke\ntournament: 20\n")
    (tmp / "page.html").write_text("<html><body>not a log</body></html>\n")
    (tmp / "typo.json5").write_text('{"trasport": {}}')
    no_joints = genome.model_dump(mode="json")
    no_joints["limbs"][0]["joints"] = []
    (tmp / "no-joints.json").write_text(json.dumps(no_joints))
    (tmp / "begun").mkdir()  # a run of the smoke profile begun there
    (tmp / "begun" / "profile.json").write_text(load_profile("smoke").model_dump_json())
    with Journal(tmp / "other") as journal:  # a run directory of run "other"
        journal.write(WorkerReady(run="other", node="n", role="trainer", host="h", pid=1))


CASES = {  # name: (arguments, exit status, what its last line says)
    "budget below one rollout": (["train", "--genome", GENOME, "--out", "t", "--steps", "100"],
                                 2, "--steps: 100 is less than one rollout, 4,096 env steps (32 "
                                 "copies x 128 steps)"),
    "no budget": (["train", "--genome", GENOME, "--out", "t", "--steps", "0"], 2,
                  "--steps: 0 is less than one rollout, 4,096 env steps"),
    "a training's folder that is a file": (["train", "--genome", GENOME, "--out", "a-file"], 1,
                                           "--out a-file is a file, not a directory"),
    "a training's folder that cannot be made": (["train", "--genome", GENOME, "--out",
                                                 "/proc/x"], 1, "cannot make --out /proc/x"),
    "a training without a body": (["train", "--out", "t"], 2, "--genome required (or --resume"),
    "a resume with a new training's flag": (["train", "--resume", "trained", "--seed", "3"],
                                            2, "--resume takes the training's settings from its "
                                            "folder: drop --seed"),
    "a resume of a finished training": (["train", "--resume", "trained"], 1,
                                        "--resume trained: its training finished (0 env steps): "
                                        "extend it with a larger --steps"),

    "a report into a folder that cannot be made": (["report", "missing", "--out", "/proc/x"], 1,
                                                   "cannot make --out /proc/x"),
    "a video format derl does not write": (["rollout", "trained", "--video", "x.avi"], 2,
                                           "--video x.avi: write a .gif, or an .mp4"),
    "a video in no folder": (["rollout", "trained", "--video", "missing/v.gif"], 1,
                             "--video missing/v.gif: no folder missing"),
    "a video where no file can be made": (["rollout", "trained", "--video", "/proc/v.gif"], 1,
                                          "--video /proc/v.gif: cannot write there ("),
    "an endpoint without a port": (["monitor", "--connect", "tcp/nonsense", "--once", "1"], 2,
                                   "argument --connect: 'tcp/nonsense' is not an endpoint: give "
                                   "tcp/HOST:PORT"),
    "an endpoint's port out of range": (["topic", "echo", "status", "--connect",
                                         "tcp/127.0.0.1:99999"], 2,
                                        "'tcp/127.0.0.1:99999': 99999 is not a port number"),
    "an impossible genome": (["train", "--genome", "no-joints.json", "--out", "t"], 1,
                             "no-joints.json is not a valid genome: limbs.0: limb 0: joints must"),
    "zero copies": (["train", "--genome", GENOME, "--out", "t", "--envs", "0"], 2,
                    "--envs: must be at least 1, not 0"),
    "zero workers": (["run", "--workers", "0"], 2, "--workers: must be at least 1, not 0"),
    "an option of another command": (["train", "--genome", GENOME, "--out", "t", "--env", "ft"],
                                     2, "unrecognized arguments: --env ft"),  # not --envs
    "an argument no option takes": (["unimal", "sample", "3", "--out", "b"], 2,
                                    "derl unimal sample: error: unrecognized arguments: 3"),
    "misspelt profile key": (["run", "--profile", "typo.yaml"], 1,
                             "unknown key 'populaton'; valid keys: name, world, population"),
    "an unknown built-in profile": (["run", "--profile", "smok.yaml"], 1,
                                    "`profile: smok` is not a built-in profile; choose smoke, "
                                    "demo, paper"),
    "an empty profile file": (["run", "--profile", "empty.yaml"], 1,
                              "the file holds no settings: start it with `profile: NAME`"),
    "a tournament larger than the population": (["run", "--profile", "big-tournament.yaml"], 1,
                                                "tournament (20) > population (4)"),
    "a negative monitor time": (["monitor", "--once", "-1"], 2,
                                "--once: must be more than 0 seconds, not -1"),
    "a report of a file that is no log": (["report", "page.html", "--out", "r"], 1,
                                          "page.html is not an MCAP log"),
    "a misspelt key in --set": (["run", "--set", "ppo.lrr=1e-4"], 2,
                                "profile smoke with --set ppo.lrr=1e-4: unknown key 'ppo.lrr'; "
                                "valid keys: rollout_steps, gamma"),
    "a --set that breaks a rule between settings": (["run", "--set", "in_flight=1000"], 2,
                                                    "profile smoke with --set in_flight=1000: "
                                                    "in_flight (1000) >= population (4)"),
    "a misspelt profile name": (["run", "--profile", "smok"], 2,
                                "profile smok: no profile 'smok': use smoke, demo, paper"),
    "a missing genome": (["train", "--genome", "missing.json", "--out", "t"], 2,
                         "missing.json: no such file"),
    "a resume of a missing folder": (["train", "--resume", "missing"], 2,
                                     "--resume missing: no such directory"),
    "a --set without a value": (["study", "--study-dir", "s", "--set", "seeds"], 2,
                                "argument --set: 'seeds' is not KEY=VALUE (e.g. ppo.lr=1e-4)"),
    "a --set of a wrong value": (["run", "--set", "total=many"], 2,
                                 "profile smoke with --set total=many: total: Input should be a "
                                 "valid integer"),
    "a node's --set of a wrong value": (["coordinator", "--run", "r", "--run-dir", "c", "--set",
                                         "total=many"], 78,
                                 "profile smoke with --set total=many: total: Input should be a "
                                 "valid integer"),
    "a job's setting under ppo": (["run", "--profile", "job-key.yaml"], 1,
                                  "unknown key 'ppo.num_envs'; valid keys: rollout_steps, gamma"),
    "misspelt launch key": (["launch", "launch.yaml", "--dry-run"], 1,
                            "unknown key 'hosts.0.nodes.0.cont'; valid keys: role, count"),
    "another value of a setting of a run begun": (["run", "--set", "total=10", "--run-dir",
                                                   "begun"], 2,
                                                  "--set total=10: the run in begun has total 8 "
                                                  "(--extend raises it)"),
    "an extension to fewer bodies": (["run", "--set", "total=6", "--extend", "--run-dir",
                                      "begun"], 2, "--set total=6: the run in begun has total 8;"),
    "a training's folder as a run directory": (["run", "--run-dir", "trained"], 2,
                                               "--run-dir trained holds a `derl train` output"),
    "run directory is a file": (["run", "--run-dir", "a-file"], 1, "a-file is a file"),
    "no run directory": (["report", "missing", "--out", "r"], 2,
                         "no run directory or log at missing"),
    "no log": (["log", "info", "missing.mcap"], 2, "missing.mcap: no such file"),
    "an export into a folder that cannot be made": (["export", "other", "--tensorboard",
                                                     "/proc/x"], 1,
                                                    "cannot make --tensorboard /proc/x"),
    "an export into a file that cannot be made": (["export", "other", "--json", "/proc/x.mcap"],
                                                  1, "cannot write --json /proc/x.mcap"),
    "bodies into a folder that cannot be made": (["unimal", "sample", "--out", "/proc/x"], 1,
                                                 "cannot make --out /proc/x"),
    "an export of nothing": (["export", "other"], 1,
                             "say what to write: --json OUT.mcap, --tensorboard LOGDIR, or both"),
    "no trained body": (["rollout", "."], 2, "holds no trained body"),
    "a video size without x": (["rollout", ".", "--video-size", "320"], 2,
                               "'320': give WIDTHxHEIGHT in pixels"),
    "unknown message type": (["schema", "Nope"], 2, "unknown message type 'Nope'; valid:"),
    "router's port in use": (["router", "--listen", "tcp/127.0.0.1:{port}"], 2,
                             "the port is in use"),
    "coordinator's port in use": (["coordinator", "--run", "r", "--run-dir", "c", "--listen",
                                   "tcp/127.0.0.1:{port}"], 2, "the port is in use"),
    "run's port in use": (["run", "--port", "{port}", "--run-dir", "x"], 2,
                          "Address already in use"),
    "study without runs": (["study", "--study-dir", "s"], 1, "s is not a study yet"),
    "study of a missing run": (["study", "missing", "--study-dir", "s"], 2,
                               "no run directory or log at missing"),
    "misspelt study key": (["study", "a-file", "--study-dir", "s", "--profile", "typo.yaml"], 1,
                           "unknown key 'populaton'; valid keys: name, per_lineage"),
    "another run's journal": (["coordinator", "--run", "r", "--run-dir", "other", "--listen",
                               "tcp/127.0.0.1:0"], 78,
                              "holds the journal of run 'other', not 'r': resume it with --run"),
    "coordinator of no study": (["coordinator", "--run", "r", "--study", "s"], 78,
                                "s is not a study (no study.json)"),
    "a monitor that hears nothing": (["monitor", "--once", "1", "--run", "r"], 1,
                                     "heard nothing of run r in 1 s (peer, connected to "
                                     "tcp/127.0.0.1:{local}, where nothing listens)"),
    "a monitor that finds no run": (["monitor", "--once", "3"], 1,  # it looks for 3 s, not 2
                                    "no run heard in 3 s (no derl/*/status, no live node) (peer, "
                                    "connected to tcp/127.0.0.1:{local}, where nothing listens)"),
    "a topic list that hears nothing": (["topic", "list", "--duration", "1"], 1,
                                        "nothing heard on derl/** in 1 s (peer, connected to "
                                        "tcp/127.0.0.1:{local}, where nothing listens)"),
    "an echo that hears nothing": (["topic", "echo", "status", "--run", "r", "--duration", "1",
                                    "--connect", "tcp/127.0.0.1:{port}"], 1,
                                   "nothing heard on status in 1 s (peer, connected to "
                                   "tcp/127.0.0.1:{port}); is the run on another endpoint?"),
    "a missing Zenoh config": (["trainer", "--run", "r", "--zenoh-config", "missing.json5"], 1,
                               "--zenoh-config missing.json5: No such file or directory"),
    "misspelt Zenoh config key": (["trainer", "--run", "r", "--zenoh-config", "typo.json5"], 1,
                                  "--zenoh-config typo.json5: JSON error: Message { msg: \"unknown "
                                  "field `trasport`"),
}  # fmt: skip


OWN_PROCESS = {  # those that open a Zenoh session or end as a node does: run in a process each
    "router's port in use", "coordinator's port in use", "run's port in use",
    "another run's journal", "coordinator of no study", "a node's --set of a wrong value",
    "a monitor that hears nothing", "a monitor that finds no run",
    "a topic list that hears nothing", "an echo that hears nothing", "a missing Zenoh config",
    "misspelt Zenoh config key",
}  # fmt: skip
"""The rest run in the test's process, as `derl.nodes.cli.main.main(argv)` (what `derl` calls):
the same exit status and standard error, without a second of imports each."""


@pytest.mark.parametrize("name", CASES)
def test_bad_input_gets_one_line_and_an_exit_status(
    name: str,
    tmp_path: Path,
    busy_port: int,
    quadruped: Genome,
    trained: dict[str, bytes],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    arguments, status, says = CASES[name]
    _files(tmp_path, quadruped, trained)
    local = free_port()  # the local run's port ($DERL_LOCAL_PORT), where nothing listens

    def filled(text: str) -> str:
        return text.replace("{port}", str(busy_port)).replace("{local}", str(local))

    argv = [filled(argument) for argument in arguments]
    if name in OWN_PROCESS:
        env = {**os.environ, "DERL_LOCAL_PORT": str(local)}
        done = subprocess.run(derl_argv(*argv), capture_output=True, text=True, cwd=tmp_path,
                              env=env, timeout=60)  # fmt: skip
        returncode, stderr = done.returncode, done.stderr
    else:
        monkeypatch.chdir(tmp_path)
        monkeypatch.setenv("DERL_LOCAL_PORT", str(local))
        try:
            returncode = main(argv)
        except SystemExit as ended:
            returncode = ended.code
        stderr = capsys.readouterr().err
    lines = stderr.strip().splitlines()
    assert returncode == status, stderr
    assert lines and filled(says) in lines[-1], stderr
    assert "Traceback" not in stderr
    assert len([line for line in lines if line.startswith("derl")]) == 1, stderr


def test_a_free_port_is_drawn_outside_the_ephemeral_range() -> None:
    """`--port 0` and the tests' endpoints: a port the kernel gives neither to a socket bound to
    port 0 (another node's listener) nor to an outgoing connection, so none takes it before its
    listener binds it (a study resumed with `--port 0` once found its port taken so)."""
    first, last = ephemeral_range()
    ports = [free_port(span=3) for _ in range(50)]
    assert not [p for p in ports if first <= p + 2 and p <= last], (first, last, ports)
    assert all(bindable("127.0.0.1", p + k) for p in ports for k in range(3))
    assert listenable(0) not in range(first, last + 1)
