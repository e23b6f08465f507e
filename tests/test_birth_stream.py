"""The birth stream as an outside monitor sees it: the README's recipe (examples/fitness_monitor.py,
only `zenoh` and `msgpack`) on a real run with forged reports on the bus and a coordinator killed
and restarted on its endpoint prints exactly the journal's births, each once, none forged."""

from __future__ import annotations

import json
import math
import os
import signal
import sys
from pathlib import Path

import msgpack
import pytest
import yaml
from nodes_fixtures import Processes, derl_argv, free_port, run_id

from derl.messages import Birth, FitnessReport, Reject, Rejection, TrainProgress, encode
from derl.messages.examples import examples
from derl.nodes.journal.segments import replay, segments
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.testing.waiting import wait_until
from derl.unimal import Genome

PROFILE = {
    "profile": "smoke",
    "population": 2,
    "in_flight": 1,
    "tournament": 2,
    "total": 5,
    "train_steps": 16384,  # 8 PPO iterations, ~1-2 s a body
    "num_envs": 16,
    "lease_s": 20.0,
    "eval_top": 0,
    "eval_tasks": [],
}


def _journal(run_dir: Path) -> list[object]:
    return list(replay(run_dir)) if segments(run_dir) else []


def _forge(bus: Bus, progress: TrainProgress, run_dir: Path) -> None:
    """Reports a trainer never made, for the job `progress` belongs to: under its name on its own
    key (an impossible fitness, another body, a non-finite fitness), under its name on another
    node's key, and under another name for its job."""
    template = next(m for m in examples(bus.run, 3) if isinstance(m, FitnessReport))
    real = {"agent": progress.agent, "job": progress.job, "node": progress.node}
    bodies = json.loads((run_dir / "initial_population.json").read_text())
    body = Genome.model_validate(bodies[int(progress.agent.removeprefix("i"))])
    impossible = template.model_copy(
        update={**real, "genome": body, "mutation": None, "fitness": 3e9}
    )
    foreign_body = template.model_copy(update={**real, "fitness": 5.0, "mutation": None})
    bus.session.put(bus.keys.fitness(progress.node, progress.agent), encode(impossible))
    bus.session.put(bus.keys.fitness(progress.node, progress.agent), encode(foreign_body))
    not_finite = {**msgpack.unpackb(encode(foreign_body)), "fitness": math.inf}
    bus.session.put(bus.keys.fitness(progress.node, progress.agent), msgpack.packb(not_finite))
    bus.session.put(bus.keys.fitness("mallory", progress.agent), encode(foreign_body))
    other_name = template.model_copy(update={**real, "node": "mallory", "fitness": 7.0})
    bus.session.put(bus.keys.fitness("mallory", progress.agent), encode(other_name))


@pytest.mark.slow
def test_a_raw_monitor_sees_exactly_the_journals_births(tmp_path: Path) -> None:
    run, endpoint, run_dir = run_id(), f"tcp/127.0.0.1:{free_port()}", tmp_path / "run"
    profile = tmp_path / "profile.yaml"
    profile.write_text(yaml.safe_dump(PROFILE))
    coordinator = derl_argv("coordinator", "--profile", str(profile), "--run-dir", str(run_dir),
                            "--run", run, "--listen", endpoint)  # fmt: skip
    procs = Processes(tmp_path / "logs")
    progress: list[TrainProgress] = []
    try:
        procs.start("coordinator", coordinator)
        wait_until(lambda: "replayed" in procs.log("coordinator"), 60, "the coordinator")
        # the test hears progress before any training starts: the forged reports must reach the
        # coordinator while their job is still in flight (a born child's reports are only acked)
        with open_session(ZenohOptions(connect=(endpoint,))) as session:
            bus = Bus(session, run)
            bus.subscribe(bus.keys.all("progress"), progress.append, (TrainProgress,))
            for name in ("a", "b"):
                procs.start(name, derl_argv("trainer", "--run", run, "--connect", endpoint,
                                            "--name", name))  # fmt: skip
            monitor = [sys.executable, "examples/fitness_monitor.py", run, endpoint]
            procs.start("monitor", monitor)
            first = wait_until(
                lambda: next((p for p in progress if 2 * p.env_steps <= p.total_steps), None),
                180,
                "a training in its first half",
            )
            # its trainer stopped until every forged report is answered: its own report comes
            # after them on a machine of any speed (SIGSTOP for well within the transport lease)
            holder = procs.started[first.node].pid
            os.killpg(holder, signal.SIGSTOP)
            try:
                _forge(bus, first, run_dir)
                wait_until(lambda: _answered(run_dir, first), 2, "the forged reports answered")
            finally:
                os.killpg(holder, signal.SIGCONT)
            wait_until(lambda: len(_births(run_dir)) >= 2, 240, "two births")
            procs.kill("coordinator")
            with segments(run_dir)[-1].open("ab") as torn:  # a write cut short by the kill
                torn.write(b"\x05torn")
            procs.start("coordinator-2", coordinator)
            wait_until(lambda: procs.started["coordinator-2"].poll() is not None, 300, "the end")
        assert procs.started["coordinator-2"].returncode == 0, procs.log("coordinator-2")
        journal = _journal(run_dir)
        births = [m for m in journal if isinstance(m, Birth)]
        assert len(births) == PROFILE["total"] == len({b.agent for b in births})
        wanted = {f"{b.agent} fitness {b.fitness:.2f} ({b.node})" for b in births}
        wait_until(
            lambda: wanted <= set(procs.log("monitor").splitlines()), 30, "every birth printed"
        )
        printed = [line for line in procs.log("monitor").splitlines() if " fitness " in line]
        assert sorted(printed) == sorted(wanted)  # each birth once, nothing else
        reasons = " | ".join(m.reason for m in journal if isinstance(m, Reject))
        for why in ("beyond what the world allows", "not the body of its job", "never issued"):
            assert why in reasons, why
        assert any(  # a name that is not its key's: journaled, not answered
            isinstance(m, Rejection) and m.sender == first.node and "/mallory/" in m.key
            for m in journal
        )
        assert all(b.fitness < 1e9 for b in births)
        # the Rejects of the forged reports are not taken for answers to the real report
        assert next(b for b in births if b.agent == first.agent).job == first.job
        assert f"{first.job} rejected" not in procs.log(first.node)
    finally:
        procs.close()
    assert all(p.poll() is not None for p in procs.started.values())


def _answered(run_dir: Path, progress: TrainProgress) -> bool:
    """Whether the coordinator journaled its answer to each report `_forge` made for the job of
    `progress`: three Rejects (two under the trainer's name, one for mallory) and the Rejection of
    the trainer's name on mallory's key (the non-finite fitness never decodes: nothing to say)."""
    journal = _journal(run_dir)
    rejects = [m for m in journal if isinstance(m, Reject) and m.job == progress.job]
    return len(rejects) >= 3 and any(
        isinstance(m, Rejection) and "/mallory/" in m.key for m in journal
    )


def _births(run_dir: Path) -> list[Birth]:
    return [m for m in _journal(run_dir) if isinstance(m, Birth)]
