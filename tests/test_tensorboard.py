"""A run's curves as TensorBoard event files, read back with TensorBoard's own reader
(EventAccumulator): `derl export --tensorboard` of a journal, and `derl tensorboard` live on real
Zenoh (loopback, multicast off) writing the same points per birth; a watcher started again in
the same directory goes on after the last step written there (TensorBoard drops the points at
and after a step that goes back)."""

from __future__ import annotations

import signal
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from nodes_fixtures import Processes, derl_argv, free_port
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from derl.messages import Birth, Curve, FitnessReport, MessageBase, RunStatus
from derl.messages.examples import examples
from derl.metrics import TensorBoardRun
from derl.nodes.journal.segments import JournalWriter
from derl.nodes.runtime.bus import Bus, ZenohOptions, matched, open_session
from derl.nodes.testing.waiting import wait_until
from derl.nodes.tools.tensorboard import TAGS, LiveRun, Scalars

FITNESS = (1.0, 2.0, 3.0, 4.0, 5.0, 2.5, 6.0)  # 4 initial bodies, then 3 children of b1
RETURNS = ((0.0, 2.0, 5.0), (0.0, 4.0, 4.0), (0.0, 1.0, 1.0))  # by body, cycling
INITIAL = 4
CRITERION = float(np.percentile(FITNESS[:INITIAL], 75))  # 3.25, as `derl report`'s


def _run(run: str) -> list[MessageBase]:
    """Each body's FitnessReport (its curve: RETURNS after 1,000, 2,000, 3,000 steps) and then
    its Birth."""
    base = examples(run, 0)
    report = next(m for m in base if isinstance(m, FitnessReport))
    birth = next(m for m in base if isinstance(m, Birth))
    messages: list[MessageBase] = []
    for k, fitness in enumerate(FITNESS):
        child, job, initial = f"b{k}", f"j{k}", k < INITIAL
        curve = Curve(env_steps=(1000, 2000, 3000), returns=RETURNS[k % len(RETURNS)])
        messages.append(report.model_copy(update={
            "agent": child, "job": job, "fitness": fitness, "curve": curve, "wall_s": 2.0,
            "steps_per_s": 1000.0 + k}))  # fmt: skip
        messages.append(birth.model_copy(update={
            "agent": child, "job": job, "birth": k, "fitness": fitness, "cost_of_work": 0.5 * k,
            "parent": None if initial else "b1", "generation": 0 if initial else 1,
            "mutation": None if initial else "grow_limb", "repeat_of": None}))  # fmt: skip
    return messages


def _speed(k: int) -> float | None:
    """Env steps body k's curve took to reach the criterion (None: never)."""
    returns = RETURNS[k % len(RETURNS)]
    reached = [steps for steps, value in zip((1000, 2000, 3000), returns, strict=True)
               if value >= CRITERION]  # fmt: skip
    return float(reached[0]) if reached else None


def _scalars(directory: Path) -> dict[str, list[tuple[int, float]]]:
    events = EventAccumulator(str(directory), size_guidance={"scalars": 0})
    events.Reload()
    return {
        tag: [(e.step, pytest.approx(e.value)) for e in events.Scalars(tag)]
        for tag in events.Tags()["scalars"]
    }


def _expected_births() -> dict[str, list[tuple[int, float]]]:
    speeds = [(k, _speed(k)) for k in range(len(FITNESS))]
    return {
        "birth/fitness": list(enumerate(FITNESS)),
        "birth/generation": [(k, 0.0 if k < INITIAL else 1.0) for k in range(len(FITNESS))],
        "birth/cost_of_work": [(k, 0.5 * k) for k in range(len(FITNESS))],
        "birth/steps_to_criterion": [(k, s) for k, s in speeds if s is not None],
    }


def test_export_writes_a_journal_as_event_files(tmp_path: Path, procs: Processes) -> None:
    run = f"r{uuid.uuid4().hex[:8]}"
    log = tmp_path / "run.mcap"
    with JournalWriter(log) as writer:
        for message in _run(run):
            writer.write(message)
    logdir = tmp_path / "tb"
    export = procs.start("export", derl_argv("export", str(log), "--tensorboard", str(logdir)))
    assert procs.finish(export, 120) == 0, procs.log("export")
    assert f"exported the run's scalars to {logdir / run}" in procs.log("export")
    got = _scalars(logdir / run)
    assert set(got) == set(TAGS)
    for tag, points in _expected_births().items():
        assert got[tag] == points, tag
    assert got["run/born"] == [(k, k) for k in range(1, len(FITNESS) + 1)]
    best = np.maximum.accumulate(FITNESS)
    assert got["run/best_fitness"] == [(k + 1, b) for k, b in enumerate(best)]
    assert got["run/failed"] == [(k, 0.0) for k in range(1, len(FITNESS) + 1)]
    again = procs.start("again", derl_argv("export", str(log), "--tensorboard", str(logdir)))
    assert procs.finish(again, 120) == 1  # a run's scalars are not written twice
    assert "holds event files already" in procs.log("again")


@pytest.fixture
def bus() -> Iterator[tuple[Bus, str]]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(ZenohOptions(listen=(endpoint,))) as session:
        yield Bus(session, f"w{uuid.uuid4().hex[:10]}"), endpoint


def _watcher(procs: Processes, name: str, bus: Bus, endpoint: str, logdir: Path) -> None:
    """Watcher `name` of `bus`'s run, once it writes and its subscriptions reach `bus`."""
    argv = derl_argv("tensorboard", "--run", bus.run, "--connect", endpoint, "--logdir",
                     str(logdir))  # fmt: skip
    procs.start(name, argv)
    wait_until(lambda: "writing run" in procs.log(name), 60, f"{name} to write")
    wait_until(lambda: _watched(bus), 30, f"{name}'s subscriptions")


def _watched(bus: Bus) -> bool:
    """Whether a watcher subscribes to every kind it takes (births, reports, status)."""
    messages = _run(bus.run)[:2]
    taps = [bus.session.declare_publisher(key)
            for key in (*map(bus.keys.key_for, messages), bus.keys.status())]  # fmt: skip
    try:
        return all(matched(tap) for tap in taps)
    finally:
        for tap in taps:
            tap.undeclare()


def _publish(bus: Bus, messages: list[MessageBase]) -> None:
    for message in messages:
        bus.publish(message)
        time.sleep(0.02)


def test_the_live_watcher_writes_what_export_writes_and_goes_on_after_a_restart(
    tmp_path: Path, procs: Processes, bus: tuple[Bus, str]
) -> None:
    """Births 0-4 to a first watcher, stopped; a second one hears every birth again (as from
    the coordinator's memory), and the rest, until the run is done: each birth's points once,
    steps never going back, and the run's status every second."""
    publisher, endpoint = bus
    run, logdir = publisher.run, tmp_path / "tb"
    messages = _run(run)
    _watcher(procs, "first", publisher, endpoint, logdir)
    _publish(publisher, messages[: 2 * 5])
    wait_until(lambda: len(_scalars(logdir / run).get("birth/fitness", [])) == 5, 30, "5 births")
    procs.kill("first", signal.SIGTERM)
    wait_until(lambda: not _watched(publisher), 30, "the first watcher's subscriptions gone")
    _watcher(procs, "second", publisher, endpoint, logdir)
    _publish(publisher, messages)
    status = RunStatus(run=run, born=len(FITNESS), target=len(FITNESS), best_fitness=6.0,
                       best_agent="b6", in_flight=0, workers_alive=2,
                       steps_per_s=1500.0)  # fmt: skip
    # the births written before the run is done
    wait_until(lambda: len(_scalars(logdir / run).get("birth/fitness", [])) == len(FITNESS), 30,
               "every birth written")  # fmt: skip
    _publish(publisher, [status.model_copy(update={"done": True})])
    assert procs.finish(procs.started["second"], 30) == 0, procs.log("second")
    got = _scalars(logdir / run)
    for tag, points in _expected_births().items():
        assert got[tag] == points, tag
    assert got["run/born"][-1] == (len(FITNESS), len(FITNESS))
    assert got["run/best_fitness"][-1] == (len(FITNESS), 6.0)
    assert got["run/steps_per_s"][-1] == (len(FITNESS), 1500.0)


def test_a_live_watcher_keeps_of_a_curve_only_what_its_birth_needs(tmp_path: Path) -> None:
    """Once the criterion is known (at the first child's birth), a report heard keeps only its
    curve's first point at the criterion: a watcher of a paper-length run does not hold every
    1,220-point curve. The points written are the same."""
    board = TensorBoardRun(tmp_path)
    live = LiveRun(Scalars(board), ask_births=lambda: None)
    heard = [(1.0, message) for message in _run("r")]
    for now, part in enumerate((heard[: 2 * (INITIAL + 1)], [], heard[2 * (INITIAL + 1) :], [])):
        live.fold(part, float(now))
    board.close()
    curves = {child: len(r.curve.env_steps) for child, r in live.history.reports.items()}
    assert curves == {"b0": 3, "b1": 3, "b2": 3, "b3": 3, "b4": 3, "b5": 0, "b6": 1}
    got = _scalars(tmp_path)
    for tag, points in _expected_births().items():
        assert got[tag] == points, tag
