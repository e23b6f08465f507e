"""The watch-and-replay tools on real Zenoh (loopback, multicast off, a fresh port and run id per
test) with real processes: record, replay (timing, filters, refusal of a live run, the line
saying nobody heard it), topic echo (through a router, as clients), hz and list, monitor --once,
and the example monitor."""

from __future__ import annotations

import io
import json
import re
import signal
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from nodes_fixtures import LocalRun, Processes, derl_argv, free_port

from derl.messages import (
    Birth,
    FitnessReport,
    MessageBase,
    RunStatus,
    Tournament,
    TrainProgress,
    encode,
    kind_of,
)
from derl.messages.examples import examples
from derl.nodes.journal.segments import JournalWriter
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.runtime.processes import stop_all
from derl.nodes.testing.waiting import wait_until
from derl.nodes.tools.logs import read_log
from derl.nodes.tools.monitor import RunView, sparkline
from derl.nodes.tools.topic import key_expression, rate_line

STEP_TYPES = {"Tournament", "TrainProgress", "FitnessReport", "Ack", "RunStatus"}
STEPS, GAP_S = 6, 0.4


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def bus(endpoint: str) -> Iterator[Bus]:
    """The test's own peer session, listening on `endpoint`, for a fresh run id."""
    with open_session(ZenohOptions(listen=(endpoint,))) as session:
        yield Bus(session, f"w{uuid.uuid4().hex[:10]}")


class Repeater:
    """Publishes the same messages (and raw payloads) every `period` s until stopped."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(
        self,
        messages: list[MessageBase],
        period: float,
        raw: tuple[tuple[str, bytes], ...] = (),
    ) -> None:
        def loop() -> None:
            while not self._stop.wait(period):
                for message in messages:
                    self.bus.publish(message)
                for key, payload in raw:
                    self.bus.session.put(key, payload)

        thread = threading.Thread(target=loop, daemon=True)
        thread.start()
        self._threads.append(thread)

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(5)


@pytest.fixture
def repeater(bus: Bus) -> Iterator[Repeater]:
    publisher = Repeater(bus)
    try:
        yield publisher
    finally:
        publisher.stop()


@pytest.fixture(scope="module")
def run_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded run: STEPS steps GAP_S apart, each a tournament, progress, fitness, ack and
    status, written by the journal's writer (its log times are the real write times)."""
    path = tmp_path_factory.mktemp("log") / "run.mcap"
    with JournalWriter(path) as writer:
        for step in range(STEPS):
            if step:
                time.sleep(GAP_S)
            for message in examples("recorded", step):
                if message.type in STEP_TYPES:
                    writer.write(message)
    return path


def _collector(bus: Bus, run: str) -> list[tuple[float, MessageBase]]:
    got: list[tuple[float, MessageBase]] = []
    watcher = Bus(bus.session, run)
    watcher.subscribe(watcher.keys.everything(), lambda m: got.append((time.monotonic(), m)))
    return got


# --- record and replay -----------------------------------------------------------------------


def test_record_keeps_every_valid_message_and_counts_garbage(
    tmp_path: Path, procs: Processes, bus: Bus, endpoint: str
) -> None:
    out = tmp_path / "recorded.mcap"
    recorder = procs.start(
        "record", derl_argv("record", str(out), "--connect", endpoint, "--duration", "60")
    )
    probe = bus.session.declare_publisher(bus.keys.status())
    wait_until(lambda: probe.matching_status.matching, 30, "the recorder's subscription")
    sent = [m for i in range(3) for m in examples(bus.run, i)]
    for message in sent:
        bus.publish(message)
    bus.session.put(bus.keys.fitness("n", "x"), b"\xff\x00garbage")
    bus.session.put(bus.keys.population(), encode(sent[-1]))  # a RunStatus on the wrong key
    wait_until(lambda: out.exists() and len(list(read_log(out))) == len(sent), 20, "the recording")
    stop_all([recorder])
    assert recorder.returncode == 0, procs.log("record")
    assert [logged.message for logged in read_log(out)] == sent
    assert f"recorded {len(sent)} messages" in procs.log("record")
    assert re.search(r"rejected: .*malformed 1", procs.log("record"))
    assert "wrong key 1" in procs.log("record")


def test_replay_keeps_order_and_scales_timing(
    run_log: Path, procs: Processes, bus: Bus, endpoint: str
) -> None:
    got = _collector(bus, "recorded")
    replay = procs.start(
        "replay", derl_argv("replay", str(run_log), "--rate", "10", "--connect", endpoint)
    )
    assert procs.finish(replay) == 0, procs.log("replay")
    expected = [logged.message for logged in read_log(run_log)]
    wait_until(lambda: len(got) >= len(expected), 10, "every replayed message")
    assert [m for _, m in got] == expected
    span = got[-1][0] - got[0][0]
    assert 0.5 * (STEPS - 1) * GAP_S / 10 < span < 1.5, span  # 2.0 s of log at 10x: 0.2 s


def test_replay_filters_kinds_skips_the_start_and_renames_the_run(
    run_log: Path, procs: Processes, bus: Bus, endpoint: str
) -> None:
    got = _collector(bus, "renamed")
    args = ["replay", str(run_log), "--rate", "0", "--topics", "fitness,status", "--start-offset",
            "1.0", "--as-run", "renamed", "--force", "--connect", endpoint]  # fmt: skip
    assert procs.finish(procs.start("replay", derl_argv(*args))) == 0, procs.log("replay")
    logged = list(read_log(run_log))
    expected = [
        entry.message.model_copy(update={"run": "renamed"})
        for entry in logged
        if kind_of(entry.message) in ("fitness", "status")
        and entry.log_time - logged[0].log_time >= 1e9
    ]
    assert len(expected) == 6  # fitness and status of the steps at 1.2, 1.6 and 2.0 s
    wait_until(lambda: len(got) >= len(expected), 10, "the filtered replay")
    time.sleep(0.3)
    assert [m for _, m in got] == expected


def test_replay_loops_until_stopped(
    run_log: Path, procs: Processes, bus: Bus, endpoint: str
) -> None:
    got = _collector(bus, "looped")
    args = ["replay", str(run_log), "--rate", "20", "--topics", "status", "--loop",
            "--as-run", "looped", "--force", "--connect", endpoint]  # fmt: skip
    replay = procs.start("replay", derl_argv(*args))
    wait_until(lambda: len(got) >= 3 * STEPS, 20, "three passes")
    stop_all([replay])
    assert replay.returncode == 0 and "passes" in procs.log("replay")
    one_pass = list(range(2, STEPS + 2))  # the RunStatus of examples(run, i) has born = i + 2
    assert [m.born for _, m in got][: 2 * STEPS] == one_pass * 2


def test_replay_says_when_nobody_heard_it(
    run_log: Path, procs: Processes, bus: Bus, endpoint: str
) -> None:
    """A replay that no subscriber matched says so in one line (at its end, or after its first
    seconds when it goes on): on a bus with nobody on it, and on one whose only watcher takes
    other keys; a replay heard says nothing of it."""
    alone = ["replay", str(run_log), "--listen", f"tcp/127.0.0.1:{free_port()}"]
    assert procs.finish(procs.start("alone", derl_argv(*alone, "--rate", "0"))) == 0
    logged = len(list(read_log(run_log)))
    assert re.search(
        rf"derl replay: nobody heard it: no subscriber matched the {logged} messages published "
        r"\(peer, listening on tcp/127\.0\.0\.1:\d+\)\n",
        procs.log("alone"),
    ), procs.log("alone")
    looping = procs.start("looping", derl_argv(*alone, "--rate", "20", "--loop"))
    told = r"nobody heard it: no subscriber matched the \d+ messages published in its first 5 s"
    wait_until(lambda: re.search(told, procs.log("looping")), 30, "the notice of a long replay")
    stop_all([looping])
    assert looping.returncode == 0 and procs.log("looping").count("nobody heard it") == 1
    watcher = Bus(bus.session, "recorded")
    statuses: list[MessageBase] = []
    watcher.subscribe(watcher.keys.status(), statuses.append)
    for topics, told in (("fitness", True), ("status", False)):
        args = ["replay", str(run_log), "--rate", "0", "--topics", topics, "--connect", endpoint]
        assert procs.finish(procs.start(topics, derl_argv(*args))) == 0, procs.log(topics)
        assert ("nobody heard it" in procs.log(topics)) is told, procs.log(topics)
    wait_until(lambda: len(statuses) == STEPS, 10, "the replayed statuses")


def test_replay_refuses_a_run_with_live_nodes(
    run_log: Path, procs: Processes, bus: Bus, endpoint: str
) -> None:
    live = Bus(bus.session, "recorded")
    got = _collector(bus, "recorded")
    token = live.token("trainer", "t0")
    replay = procs.start(
        "replay", derl_argv("replay", str(run_log), "--rate", "0", "--connect", endpoint)
    )
    assert procs.finish(replay) == 1
    token.undeclare()
    assert "run recorded is live" in procs.log("replay")
    assert "Traceback" not in procs.log("replay")
    assert got == []


def test_watch_alive_takes_only_tokens_of_the_key_space(bus: Bus) -> None:
    seen: list[tuple[str, str, bool]] = []
    token = bus.token("trainer", "t0")
    stray = bus.session.liveliness().declare_token(f"derl/{bus.run}/alive/trainer/b@d")
    bus.watch_alive(lambda role, node, up: seen.append((role, node, up)))
    wait_until(lambda: seen, 10, "the token")
    token.undeclare()
    wait_until(lambda: len(seen) >= 2, 10, "the token gone")
    stray.undeclare()
    later = bus.token("trainer", "t1")  # seen after the stray one's end would have been
    wait_until(lambda: len(seen) >= 3, 10, "the later token")
    later.undeclare()
    wait_until(lambda: len(seen) >= 4, 10, "the later token gone")
    assert seen == [
        ("trainer", "t0", True),
        ("trainer", "t0", False),
        ("trainer", "t1", True),
        ("trainer", "t1", False),
    ]


# --- topic -----------------------------------------------------------------------------------


def test_topic_echo_prints_json_lines_through_a_router(procs: Processes) -> None:
    router = f"tcp/127.0.0.1:{free_port()}"
    procs.start("router", derl_argv("router", "--listen", router))
    run = f"w{uuid.uuid4().hex[:10]}"
    with open_session(ZenohOptions(mode="client", connect=(router,))) as session:
        publisher = Repeater(Bus(session, run))
        report = next(m for m in examples(run, 0, 300) if isinstance(m, FitnessReport))
        publisher.start([report], 0.1, raw=((f"derl/{run}/fitness/n/x", b"\xffjunk"),))
        try:
            args = ["topic", "echo", "fitness", "--run", run, "--count", "3",
                    "--mode", "client", "--connect", router]  # fmt: skip
            echo = procs.start("echo", derl_argv(*args))
            assert procs.finish(echo) == 0, procs.log("echo")
        finally:
            publisher.stop()
    lines = [json.loads(line) for line in procs.log("echo").splitlines() if line[:1] == "{"]
    assert len(lines) == 3
    assert lines[0]["checkpoint"] == {"bytes": 300}
    assert lines[0] == {
        **report.model_dump(mode="json", exclude={"checkpoint"}),
        "checkpoint": {"bytes": 300},
    }
    assert "rejected (malformed)" in procs.log("echo")


def test_topic_echo_ends_when_the_run_does(
    procs: Processes, bus: Bus, repeater: Repeater, endpoint: str
) -> None:
    status = next(m for m in examples(bus.run, 0) if isinstance(m, RunStatus))
    repeater.start([status.model_copy(update={"done": True})], 0.2)
    echo = procs.start("echo", derl_argv("topic", "echo", "fitness", "--run", bus.run,
                                         "--connect", endpoint))  # fmt: skip
    assert procs.finish(echo) == 0, procs.log("echo")
    assert f"derl topic echo: run {bus.run} is done; 0 messages shown" in procs.log("echo")


def test_topic_hz_and_list(procs: Processes, bus: Bus, repeater: Repeater, endpoint: str) -> None:
    status = next(m for m in examples(bus.run, 0) if isinstance(m, RunStatus))
    repeater.start([status], 0.05, raw=((bus.keys.fitness("n", "x"), b"\xffjunk"),))
    flags = ["--run", bus.run, "--connect", endpoint]
    rate = procs.start("hz", derl_argv("topic", "hz", "status", "--duration", "3", *flags))
    listing = procs.start("list", derl_argv("topic", "list", "--duration", "2", *flags))
    assert procs.finish(rate) == 0 and procs.finish(listing) == 0
    measured = re.findall(r"average rate: ([\d.]+) Hz", procs.log("hz"))
    assert measured and 10 < float(measured[-1]) < 30, procs.log("hz")
    assert re.search(rf"derl/{bus.run}/status\s+RunStatus\s+\d+", procs.log("list"))
    assert re.search(rf"derl/{bus.run}/fitness/n/x\s+rejected\s+\d+", procs.log("list"))


def test_watchers_given_no_endpoint_find_the_local_run(
    tmp_path: Path, procs: Processes, run_log: Path
) -> None:
    """`derl topic list` and `derl monitor` with no flag connect to the local run's endpoint
    ($DERL_LOCAL_PORT here, 7447 for a user), where a real coordinator listens, and find its
    run; with nothing there, `derl replay` listens on it and they hear the replay."""
    run = LocalRun.at(tmp_path)
    local = {"DERL_LOCAL_PORT": run.endpoint.rsplit(":", 1)[1]}
    procs.start("coordinator", run.coordinator())
    listing = procs.start("list", derl_argv("topic", "list", "--duration", "3"), local)
    monitor = procs.start("monitor", derl_argv("monitor", "--once", "3"), local)
    assert procs.finish(listing) == 0, procs.log("list")
    assert re.search(rf"derl/{run.run}/status\s+RunStatus\s+\d+", procs.log("list"))
    assert procs.finish(monitor) == 0, procs.log("monitor")
    assert f"derl run {run.run}" in procs.log("monitor")
    procs.kill("coordinator", signal.SIGTERM)
    replay = procs.start("replay", derl_argv("replay", str(run_log), "--loop"), local)
    listing = procs.start("list-replay", derl_argv("topic", "list", "--duration", "3"), local)
    assert procs.finish(listing) == 0, procs.log("list-replay")
    assert "derl/recorded/status" in procs.log("list-replay")
    stop_all([replay])


# --- monitor and the example -----------------------------------------------------------------


def _a_run(run: str) -> list[MessageBase]:
    birth = next(m for m in examples(run, 0) if isinstance(m, Birth))
    return [
        RunStatus(run=run, born=7, target=40, best_fitness=12.5, best_agent="a3", in_flight=2,
                  workers_alive=2, evaluated=1, eval_target=4, steps_per_s=2345.0),
        TrainProgress(run=run, agent="a9", job="j9", node="trainer-1", env_steps=4096,
                      total_steps=8192, recent_return=1.5, steps_per_s=1200.0),
        Tournament(run=run, agent="a8", contestants=("a3", "a1"), fitness=(12.5, 3.0),
                   parent="a3", mutation_seed=5, iteration=5),
        birth.model_copy(update={"agent": "a8", "parent": "a3", "fitness": 9.75}),
    ]  # fmt: skip


def test_monitor_once_shows_the_run(
    procs: Processes, bus: Bus, repeater: Repeater, endpoint: str
) -> None:
    repeater.start(_a_run(bus.run), 0.2)
    monitor = procs.start("monitor", derl_argv("monitor", "--once", "2", "--connect", endpoint))
    assert procs.finish(monitor) == 0, procs.log("monitor")
    text = procs.log("monitor")
    for shown in (f"derl run {bus.run}", "born 7/40", "best 12.50 (a3)", "2,345 steps/s",
                  "evaluated 1/4", "trainer-1", "4,096/8,192 (50%)", "1.50", "grow_limb",
                  "9.75", "fitness over 1 births"):  # fmt: skip
        assert shown in text, f"{shown!r} not in\n{text}"


def test_a_flood_of_junk_gives_a_few_warnings_and_a_count(
    procs: Processes, bus: Bus, repeater: Repeater, endpoint: str
) -> None:
    """Every node and tool warns about a rejected sample; under a flood (here 50 junk samples
    every 0.1 s) it printed one line each, hundreds a second. Now: the first few, then a count."""
    junk = tuple((bus.keys.status(), b"\xffjunk %d" % k) for k in range(50))
    repeater.start(_a_run(bus.run)[:1], 0.1, raw=junk)
    monitor = procs.start(
        "monitor", derl_argv("monitor", "--once", "2", "--run", bus.run, "--connect", endpoint)
    )
    procs.finish(monitor)
    lines = procs.log("monitor").splitlines()
    rejected = [line for line in lines if "WARNING rejected (malformed)" in line]
    counts = [line for line in lines if "more like it in 10 s, not shown" in line]
    assert len(rejected) == 5, lines
    assert len(counts) == 1 and int(counts[0].split("... and ")[1].split()[0]) > 5, counts


def test_example_monitor_prints_fitness(
    procs: Processes, bus: Bus, repeater: Repeater, endpoint: str
) -> None:
    reports = [m for i in range(3) for m in examples(bus.run, i) if isinstance(m, Birth)]
    repeater.start(reports, 0.2, raw=((bus.keys.births("x"), b"\xffjunk"),))
    procs.start("example", [sys.executable, "examples/fitness_monitor.py", bus.run, endpoint])
    wanted = {f"{r.agent} fitness {r.fitness:.2f} ({r.node})" for r in reports}
    wait_until(lambda: wanted <= set(procs.log("example").splitlines()), 30, "fitness lines")
    lines = procs.log("example").splitlines()
    assert sum(line in wanted for line in lines) == 3  # each child once
    assert any(line.startswith("skipped derl/") for line in lines)


@pytest.mark.parametrize("late", [False, True], ids=["answered", "answered-late"])
@pytest.mark.parametrize("watcher", ["example", "monitor"])
def test_a_birth_never_published_is_asked_for_again(
    watcher: str, late: bool, procs: Processes, bus: Bus, endpoint: str
) -> None:
    """A birth the coordinator journaled but never published (it was killed in between): once
    the status counts it, the example monitor and `derl monitor` ask again and show it; and
    again while the answer falls short (`late`: the first question after the status is answered
    with nothing, as when the restarted coordinator's queryable is not reached yet)."""
    birth = next(m for m in examples(bus.run, 0) if isinstance(m, Birth))
    status = next(m for m in examples(bus.run, 0) if isinstance(m, RunStatus))
    journaled: list[Birth] = []  # what the coordinator's query answers
    held: list[Birth] = []  # what it answers from the next question on
    asked: list[float] = []

    def answer(query: zenoh.Query) -> None:
        asked.append(time.monotonic())
        for b in list(journaled):
            query.reply(bus.keys.births(b.agent), encode(b))
        journaled.extend(held)
        held.clear()

    queryable = bus.session.declare_queryable(bus.keys.all("births"), answer)
    try:
        argv = {
            "example": [sys.executable, "examples/fitness_monitor.py", bus.run, endpoint],
            "monitor": derl_argv(
                "monitor", "--once", "15", "--run", bus.run, "--connect", endpoint
            ),
        }[watcher]
        started = time.monotonic()
        procs.start(watcher, argv)
        # its question at start is answered with nothing (or, before it knew of the queryable,
        # not at all)
        wait_until(lambda: asked or time.monotonic() > started + 8, 10, "the question at start")
        # journaled, and the coordinator killed before publishing it
        (held if late else journaled).append(birth)
        counts = status.model_copy(update={"born": 1, "failed": 0})
        for _ in range(8):  # the restarted coordinator's status, once a second
            bus.publish(counts)
            time.sleep(0.5)
        shown = f"{birth.agent} fitness {birth.fitness:.2f}" if watcher == "example" else "born 1/"
        wait_until(lambda: shown in procs.log(watcher), 20, "the birth asked for again")
        if watcher == "monitor":
            assert procs.finish(procs.started["monitor"]) == 0, procs.log("monitor")
            assert "fitness over 1 births" in procs.log("monitor")
    finally:
        queryable.undeclare()


# --- without a bus ---------------------------------------------------------------------------


def test_run_view_folds_births_and_draws_them() -> None:
    from rich.console import Console

    view = RunView("r")
    for message in _a_run("r"):
        view.apply(message, 100.0)
    view.apply(_a_run("r")[-1], 101.0)  # a birth heard twice (query and stream) is one
    assert [(b.agent, b.parent, b.mutation, b.fitness) for b in view.births] == [
        ("a8", "a3", "grow_limb", 9.75)
    ]
    assert view.best() == (12.5, "a3")
    console = Console(width=160, record=True, file=io.StringIO())
    console.print(view.render(102.0))
    assert "4,096/8,192 (50%)" in console.export_text()


def test_sparkline_key_expressions_and_rates() -> None:
    assert sparkline([0, 1, 2, 3, 4, 5, 6, 7]) == "▁▂▃▄▅▆▇█"
    assert sparkline([5.0, 5.0]) == "▁▁" and sparkline([]) == ""
    assert len(sparkline(list(range(1000)), width=10)) == 10
    assert key_expression("fitness", "r1") == "derl/r1/fitness/**"
    assert key_expression("**", "r1") == "derl/r1/**"
    assert key_expression("derl/*/status") == "derl/*/status"
    assert rate_line((0.0, 0.1, 0.2, 0.3)).startswith("average rate: 10.000 Hz")
    assert rate_line((1.0,)) == "no new messages"
