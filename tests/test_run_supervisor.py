"""`derl run` supervises its nodes: a SIGKILLed trainer and a SIGKILLed coordinator are started
again (the coordinator alone, on the same endpoint, resuming from its journal), every body is
born once, the run finishes, and the progress view (a Zenoh peer of the coordinator's endpoint)
follows the run across the restart. A run stopped with Ctrl-C prints the command that resumes
it. A run its coordinator refuses stops at once with the coordinator's reason."""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
from pathlib import Path

import pytest
from nodes_fixtures import (
    Processes,
    assert_born_once,
    births,
    derl_argv,
    free_port,
    jobs,
    journaled,
    pid_alive,
)
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from derl.evolution import load_profile
from derl.messages import Birth, RunStatus
from derl.nodes.cli.run import FREE_RUNNING, TrainingRate, fingerprint_line
from derl.nodes.errors import REFUSED
from derl.nodes.launch.commands import NodeCommand
from derl.nodes.launch.supervisor import Supervisor
from derl.nodes.testing.waiting import wait_until

COORDINATOR = "local-coordinator-0"  # the node names of launch/local.yaml


def _pids(log: str) -> dict[str, list[int]]:
    started: dict[str, list[int]] = {}
    for name, pid in re.findall(r"(\S+) started \(pid (\d+)\)", log):
        started.setdefault(name, []).append(int(pid))
    return started


@pytest.mark.slow
def test_run_restarts_a_killed_trainer_and_a_killed_coordinator(tmp_path: Path) -> None:
    run_dir, port = tmp_path / "run", free_port()
    processes = Processes(tmp_path / "test-logs")
    try:
        run = processes.start("run", derl_argv("run", "--profile", "smoke", "--run-dir",
                                               str(run_dir), "--port", str(port)))  # fmt: skip
        # the trainer that got the first job (the other may not be ready by then)
        first = wait_until(lambda: jobs(run_dir), 120, "the first job")[0].node
        other = {"local-trainer-0": "local-trainer-1", "local-trainer-1": "local-trainer-0"}[first]
        os.killpg(_pids(processes.log("run"))[first][0], signal.SIGKILL)
        wait_until(lambda: f"{first} exited with -9: restart 1/" in processes.log("run"), 10,
                   "derl run noticing the killed trainer")  # fmt: skip
        wait_until(lambda: len(births(run_dir)) >= 2, 120, "two births")
        assert len(births(run_dir)) < 8, "the run ended before the coordinator could be killed"
        os.killpg(_pids(processes.log("run"))[COORDINATOR][0], signal.SIGKILL)
        wait_until(lambda: f"{COORDINATOR} exited with -9: restart 1/" in processes.log("run"), 10,
                   "derl run noticing the killed coordinator")  # fmt: skip
        wait_until(lambda: run.poll() is not None, 240, "derl run to finish the run")
        log = processes.log("run")
        assert run.returncode == 0, log
        pids = _pids(log)
        assert len(pids[COORDINATOR]) == 2 and len(pids[first]) == 2, pids
        assert len(pids[other]) == 1 and len(pids["local-evaluator-0"]) == 1, pids  # untouched
        assert_born_once(run_dir, 8)
        # the progress view heard the restarted coordinator; the rate is the run's mean, not 0
        assert re.search(r"done: 8 bodies, best [ic]\d+ \(.+\), [1-9][\d,]* env steps/s", log), log
        assert f"tcp/127.0.0.1:{port}" in log
        coordinator_log = (run_dir / "logs" / f"{COORDINATOR}.log").read_text()
        assert "journaled messages replayed" in coordinator_log.split("start 1:")[-1]
        assert not [pid for ps in pids.values() for pid in ps if pid_alive(pid)]
    finally:
        processes.close()


def test_the_rate_shown_once_the_run_is_done_is_the_mean_while_it_trained() -> None:
    """While the run goes on the current rate; when done (nothing trains: 0) the mean of the
    rates shown while something trained, each status counted once however often shown."""
    rate = TrainingRate()

    def status(steps_per_s: float, done: bool = False) -> RunStatus:
        return RunStatus(run="r", born=1, target=2, in_flight=1, workers_alive=2,
                         steps_per_s=steps_per_s, done=done)  # fmt: skip

    first = status(1000.0)
    assert rate.shown(first).steps_per_s == 1000.0
    assert rate.shown(first).steps_per_s == 1000.0  # shown again before the next status
    assert rate.shown(status(0.0)).steps_per_s == 0.0  # nothing trains for a moment
    assert rate.shown(status(4000.0)).steps_per_s == 4000.0
    assert rate.shown(status(0.0, done=True)).steps_per_s == 2500.0
    assert TrainingRate().shown(status(0.0, done=True)).steps_per_s == 0.0


@pytest.mark.slow
def test_a_stopped_run_prints_the_command_that_resumes_it(tmp_path: Path) -> None:
    """Ctrl-C: `derl run` stops every node and prints the command that resumes the run, with
    its --set changes (a profile file's run refuses to resume under another profile) and its
    port; that command finishes it with the same settings. The run id comes from a folder name
    of any characters (`über run`: `uber-run`)."""
    run_dir = tmp_path / "über run"
    processes = Processes(tmp_path / "test-logs")
    try:
        board, port = tmp_path / "tb", free_port()
        # eval_top 0: no evaluator (what is tested here is the stop and the resume)
        argv = ["run", "--profile", "smoke", "--set", "total=6", "--set", "ppo.lr=1e-4", "--set",
                "eval_top=0", "--seed", "3", "--run-dir", str(run_dir), "--tensorboard",
                str(board)]  # fmt: skip
        run = processes.start("run", derl_argv(*argv, "--port", str(port)))
        wait_until(lambda: births(run_dir), 120, "a birth")
        run.send_signal(signal.SIGINT)
        assert run.wait(timeout=30) == 130
        said = re.search(r"stopped; `(derl run .+)` resumes the run", processes.log("run"))
        assert said is not None, processes.log("run")
        assert said[1] == (f"derl run --profile smoke --set total=6 --set ppo.lr=1e-4 "
                           f"--set eval_top=0 --seed 3 "
                           f"--run-dir '{run_dir}' --port {port} "
                           f"--tensorboard {board}")  # fmt: skip
        again = processes.start("again", derl_argv(*shlex.split(said[1])[1:], "--port",
                                                   str(free_port())))  # fmt: skip
        assert again.wait(timeout=240) == 0, processes.log("again")
        assert_born_once(run_dir, 6)
        saved = json.loads((run_dir / "profile.json").read_text())
        assert (saved["total"], saved["ppo"]["lr"]) == (6, 1e-4)
        resumed = (run_dir / "logs" / f"{COORDINATOR}.log").read_text().split("start 0:")[-1]
        assert "saved settings" not in resumed  # the resume asked for the run's own settings
        # the run's curves in TensorBoard, each birth once across the two watchers
        events = EventAccumulator(str(board / "uber-run"), size_guidance={"scalars": 0})
        events.Reload()
        assert [e.step for e in events.Scalars("birth/fitness")] == list(range(6))
        assert events.Scalars("run/born")[-1].value == 6
        # each child's training from its trainer, as `derl train --tensorboard` writes one
        born = {m.agent for m in journaled(run_dir, Birth) if m.repeat_of is None}  # trained
        children = board / "uber-run" / "children"
        assert born <= {p.name for p in children.iterdir()}
        child = EventAccumulator(str(children / sorted(born)[-1]), size_guidance={"scalars": 0})
        child.Reload()
        tags = set(child.Tags()["scalars"])
        assert {"rollout/ep_rew_mean", "train/approx_kl", "train/entropy", "time/fps"} <= tags
        steps = [e.step for e in child.Scalars("train/approx_kl")]
        assert steps == sorted(set(steps)) and steps[-1] == 8192  # smoke's lifetime, once each
    finally:
        processes.close()


def test_a_free_running_run_says_what_it_gives_up_and_claims_no_reproducibility() -> None:
    windowed, free = load_profile("smoke"), load_profile("smoke", [("in_flight", 0)])
    assert fingerprint_line("ab12", windowed).endswith("on any number of trainers)")
    assert fingerprint_line("ab12", free) == "fingerprint ab12 (a hash of the births)"
    assert "do not give the same run again" in FREE_RUNNING


def test_a_run_its_coordinator_refuses_stops_at_once_with_the_reason(tmp_path: Path) -> None:
    """A refusal no restart can change (here a run directory of another profile) stops `derl run`
    at once, with the coordinator's reason as its last line and the refusal's exit status; it
    used to restart the coordinator 10 times over 3 minutes, then print the failed command as
    the one that resumes the run."""
    run_dir = tmp_path / "smoke-run"
    run_dir.mkdir()
    (run_dir / "profile.json").write_text(load_profile("smoke").model_dump_json())
    argv = ["run", "--profile", "demo", "--run-dir", str(run_dir), "--port", "0", "--workers", "1"]
    processes = Processes(tmp_path / "test-logs")
    try:
        run = processes.start("run", derl_argv(*argv))
        assert processes.finish(run, 60) == REFUSED, processes.log("run")
    finally:
        processes.close()
    lines = processes.log("run").strip().splitlines()
    assert lines[-1].startswith("derl: the coordinator refused: ") and (
        f"{run_dir} holds a run of profile smoke" in lines[-1]
    ), lines
    assert not [line for line in lines if "restart 1/" in line or "resumes the run" in line]


def test_a_node_whose_exit_says_no_restart_helps_is_not_restarted(tmp_path: Path) -> None:
    """A worker that exits with a `FINAL` status (here 2: a usage error) is not started again."""
    command = NodeCommand(host="local", name="w", role="trainer",
                          args=("trainer", "--no-such-flag"), max_restarts=3)  # fmt: skip
    assert Supervisor([command], tmp_path).run(poll_s=0.1) == 1
    assert (tmp_path / "w.log").read_text().count("--- derl launch, start") == 1
