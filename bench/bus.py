"""Benchmark of the bus and the coordinator at scale; prints JSON.

1. `assignments`: a real `derl coordinator` process (paper population P=576, T=4, a budget of
   bodies that never runs out, lease 1 h) on loopback, driven by `LoadGenerator`: a LOAD-TEST
   TOOL that simulates W workers over one Zenoh session. Nothing is bred or trained: each
   simulated worker sends WorkerReady (again while idle, as often as a real one), and
   answers each TrainJob with a tiny fake FitnessReport the coordinator accepts (the job's body,
   which the coordinator bred; env steps within the job's PPO budget; a fitness within the
   world's bound). So children have bodies of their own, and a child whose body is born
   already, or bred like a child in training, takes the coordinator's repeat path as in a run.
   Every Reject it gets is counted. For W = 100, 1,000,
   10,000 it measures, after the initial population is born, (a) `saturated`: answers at
   once, i.e. the most assignments/s the coordinator gives; (c) `half_capacity`: each simulated
   worker's cycle (ask, job, report, Ack: its round trips included) lasts W / R s with R = half
   of (a), so the workers offer R assignments/s; (b) `paced`: the same with R = 1,000/s (the
   goal's load), run after (c); each window opens once the previous pace's jobs are over. For
   each: assignments/s, ready-to-job latency
   p50/p99/max (from the moment a worker became idle until its job arrived), and the CPU use
   of the coordinator and of the load generator (on a small machine they share the cores).
   `work` gives what creating a file costs in the runs' folder (`--work`): the coordinator
   creates one per birth, and on a file system where that takes a millisecond of CPU its
   checkpoint writer takes a core from the others at a thousand births a second.
2. `coordinator_profile`: the coordinator's own code (no bus, no network) driven in this process
   with K jobs in flight, each report carrying its job's body (a child whose body is born already
   is born as a repeat, without training, as in a run; their share is printed): CPU ms of its
   loop's thread per assignment, decoding the report and breeding the next child included (what
   bounds its rate; the checkpoint files are written by another thread) and the top functions
   (cProfile), to show where the time goes.
3. `journal`: write and replay rates of the MCAP journal (`nodes.journal.segments`) for its real mix
   (Tournament, TrainJob with a genome, FitnessReport with a learning curve, Ack), flushed
   after every message and after groups of 4 and 16 (the coordinator's group commit).
4. `recovery`: a synthetic 4,000-body journal of the paper's profile (made by driving the
   coordinator's own handlers; 64 jobs in flight at its end), the time
   the coordinator takes to replay it, and the time a real `derl coordinator`
   process started on it takes to serve (its first RunStatus, and the job it sends again to a
   worker that held one): the restart time of a paper-sized run.
5. `bus_share`: the bus's share of a trainer's wall time: every publish a real trainer makes
   during a real short training (learn() with the worker's progress cadence, through a real
   Zenoh session), plus the CPU the open session's own threads use, extrapolated to a
   paper-length training (5M steps) at the measured speed.
6. `memory`: what the coordinator's memory grows by per birth over a paper-length run (4,000
   births, 2 simulated workers, its handlers driven in this process as in 2.), each report
   carrying a learning curve of a 5M-step training's length (1,220 points): the resident memory
   of this process every 500 births, and its growth per birth from the first sample on.

Run: python bench/bus.py [--workers 100,1000,10000] [--duration 8] [--only SECTIONS] [--skip-train]
(about 4 minutes on an idle 2-core machine)
"""

from __future__ import annotations

import argparse
import cProfile
import gc
import heapq
import io
import json
import os
import pstats
import queue
import random
import shutil
import statistics
import sys
import tempfile
import threading
import time
from collections import Counter, deque
from pathlib import Path

import msgpack
import numpy as np
import yaml
import zenoh

from derl.evolution import EvolutionConfig, load_profile
from derl.evolution.evolution import breed
from derl.messages import (
    Curve,
    FitnessReport,
    KeySpace,
    MessageBase,
    RunStatus,
    Tournament,
    TrainJob,
    TrainProgress,
    WorkerReady,
    decode,
    encode,
)
from derl.nodes.coordinator.node import Liveliness
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.runtime.ports import free_port
from derl.nodes.testing.trainers import fake_report, untrained_policy
from derl.nodes.testing.waiting import wait_until
from derl.nodes.worker.node import ready_wait
from derl.unimal import Genome, sample_population

SCALE_PROFILE = {
    "profile": "paper",
    "total": 10_000_000,  # never runs out during a benchmark
    "train_steps": 4096,  # one rollout of 32 copies (the least PPO takes); nothing is trained
    "lease_s": 3600.0,
    "eval_top": 0,
    "eval_tasks": [],
}
GOAL_RATE = 1000.0
WINDOW = [("timing", "window")]  # the coordinator's own pace, not a virtual clock's
# the coordinator's Zenoh config: its session stamps each sample it puts with the time (HLC), so
# the generator can tell the coordinator's part of a latency from its own
TIMESTAMPING = {"timestamping": {"enabled": True}}
MAX_SETTLE_S = 10.0  # the longest a phase settles before its window opens
SLOW_FILE_S = 100e-6  # creating a file slower than this is worth a warning
PAPER_CURVE_POINTS = 5_000_000 // 4096  # a 5M-step training's curve: a point per rollout
BODIES = 16  # sampled bodies; the initial population is them and children of them


def _percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    return float(np.percentile(np.asarray(values), q))


def _ms(value: float | None) -> float | None:
    return None if value is None else round(value * 1e3, 2)


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process `pid` (all threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


_BODIES: list[Genome] = []


def bodies() -> list[Genome]:
    if not _BODIES:
        _BODIES.extend(sample_population(BODIES, np.random.default_rng(7)))
    return _BODIES


def seed_run_dir(run_dir: Path, population: int) -> None:
    """An initial population written ahead (sampling 576 bodies takes about a minute and is
    not what is measured): the sampled bodies and one-mutation children of them, as many
    distinct bodies as a drawn population has (few of a run's children are then repeats)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    sampled = bodies()
    genomes = sampled + [breed(sampled[k % BODIES], k)[0] for k in range(population - BODIES)]
    (run_dir / "initial_population.json").write_text(
        json.dumps([genome.model_dump() for genome in genomes[:population]])
    )


# --- 1. the load generator -----------------------------------------------------------------


class LoadGenerator:
    """LOAD-TEST TOOL: W simulated workers on one Zenoh session; they never train.

    Each simulated worker (node id ``loadgen-NNNNN``) behaves like `nodes.worker.node` minus the
    training: it announces WorkerReady, re-sends it while idle (`ready_wait`), answers each new
    TrainJob with a fake FitnessReport on its own key
    (``fitness/<node>/<agent>``: a tournament child's first draft, random fitness, a two-point
    curve within the job's budget, an untrained policy of the body), and asks for work again
    once the report is acknowledged, or rejected (counted: the coordinator must accept every
    report of this generator). With `cycle_s` set, a worker's cycle (ask, job, report, Ack)
    lasts `cycle_s` times a jitter of 0.5-1.5, its round trips included, so W workers offer
    W / `cycle_s` assignments a second; else (0) it answers at once."""

    def __init__(self, run: str, endpoint: str, workers: int) -> None:
        self.run, self.keys = run, KeySpace(run)
        self.nodes = [f"loadgen-{k:05d}" for k in range(workers)]
        self.session = zenoh.open(_peer_config(endpoint))
        self.lock = threading.Lock()
        self.idle_since: dict[str, float] = {}  # node -> when it became idle
        self.idle_wall: dict[str, float] = {}  # the same moment by the wall clock (`time.time`)
        self.last_ready: dict[str, tuple[float, int]] = {}  # node -> (when, asks unanswered)
        # (time, latency, child, the coordinator's part of the latency: None if not stamped)
        self.received: list[tuple[float, float, str, float | None]] = []
        self.ack_wait: dict[str, float] = {}  # node -> its last report's wait for the Ack
        self.seen: set[str] = set()  # job ids received
        self.repeated = 0
        self.rejected: Counter[str] = Counter()  # Reject reasons (none expected)
        self.cancelled = 0
        self.cycle_s = 0.0
        self.jitter = random.Random(0)
        # answers to send: (node, job, child, the job's genome, its step budget); job "" asks
        # for work
        self.answers: queue.Queue[tuple[str, str, str, dict | None, int]] = queue.Queue()
        # The generator shares the cores with the coordinator, so it does no more than a worker
        # must: each node's WorkerReady is encoded once, and a report is a template's fields
        # filled in and packed as `encode` packs it, not validated again
        self.ready_payload: dict[str, bytes] = {}
        self.report = FitnessReport(
            run=run, agent="c", job="j", node="n", genome=bodies()[0], fitness=0.0,
            fitness_source="window", fitness_episodes=1,
            curve=Curve(env_steps=(1, 2), returns=(0.0, 1.0)), energy=1.0, cost_of_work=1.0,
            mass=1.0, episodes=1, env_steps=1, wall_s=0.0, steps_per_s=0.0, checkpoint=b"",
        ).model_dump(mode="python")  # fmt: skip
        self.due: list[tuple[float, int, tuple]] = []  # heap of (when, order, answer)
        self.stop = threading.Event()
        self.sequence = 0
        self.tokens = [  # a worker without one gets no job
            self.session.liveliness().declare_token(self.keys.alive("trainer", node))
            for node in self.nodes
        ]
        self.subscribers = [
            self.session.declare_subscriber(self.keys.all("job"), self._on_job),
            self.session.declare_subscriber(self.keys.all("ack"), self._on_ack),
        ]
        # job -> (node, when): answered, not yet acknowledged
        self.unacked: dict[str, tuple[str, float]] = {}
        self.acked: list[tuple[float, float]] = []  # (time, wait of a report for its Ack)
        self.threads = [threading.Thread(target=f, daemon=True)
                        for f in (self._answer, self._resend, self._scheduler)]  # fmt: skip

    def start(self) -> None:
        self.started = time.perf_counter()
        for thread in self.threads:
            thread.start()
        now = time.perf_counter()
        for node in self.nodes:
            self._ready(node, now)

    def close(self) -> None:
        self.stop.set()
        for subscriber in self.subscribers:
            subscriber.undeclare()
        for thread in self.threads:
            thread.join(timeout=5)
        self.session.close()

    def _put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def _ready(self, node: str, now: float) -> None:
        with self.lock:
            self.idle_since.setdefault(node, now)
            self.idle_wall.setdefault(node, time.time())
            asks = self.last_ready[node][1] + 1 if node in self.last_ready else 0
            self.last_ready[node] = (now, asks)
        payload = self.ready_payload.get(node)
        if payload is None:
            ready = WorkerReady(run=self.run, node=node, role="trainer", host="loadgen", pid=1)
            payload = self.ready_payload[node] = encode(ready)
        self._put(self.keys.ready(node), payload)

    def _on_job(self, sample: zenoh.Sample) -> None:
        now = time.perf_counter()
        # the coordinator's session stamps what it publishes (`TIMESTAMPING`) when it puts it
        put_at = sample.timestamp.get_time().timestamp() if sample.timestamp else None
        job = msgpack.unpackb(sample.payload.to_bytes())
        if job["type"] != "TrainJob":  # a Cancel (never expected here: one worker per child)
            with self.lock:
                self.cancelled += 1
            return
        node = job["node"]
        with self.lock:
            if job["job"] in self.seen:  # a re-sent job (the worker asked again): done already
                self.repeated += 1
                return
            self.seen.add(job["job"])
            since, wall = self.idle_since.pop(node, None), self.idle_wall.pop(node, None)
            self.last_ready.pop(node, None)
            if since is not None:
                part = None if put_at is None or wall is None else put_at - wall
                self.received.append((now, now - since, job["agent"], part))
            # the job lasts what is left of the worker's cycle (cycle_s, jittered) once its
            # round trips (this job's, its last report's Ack) are taken out: so W workers offer
            # W / cycle_s assignments a second whatever the round trips take
            spent = (now - since if since is not None else 0.0) + self.ack_wait.get(node, 0.0)
        answer = (node, job["job"], job["agent"], job["genome"], job["ppo"]["total_steps"])
        delay = self.cycle_s * self.jitter.uniform(0.5, 1.5) - spent if self.cycle_s > 0 else 0.0
        if delay <= 0:
            self.answers.put(answer)
        else:
            with self.lock:
                self.sequence += 1
                heapq.heappush(self.due, (now + delay, self.sequence, answer))

    def _scheduler(self) -> None:
        while not self.stop.is_set():
            now = time.perf_counter()
            with self.lock:
                while self.due and self.due[0][0] <= now:
                    self.answers.put(heapq.heappop(self.due)[2])
            time.sleep(0.002)

    def _answer(self) -> None:
        while not self.stop.is_set():
            try:
                node, job, child, genome, budget = self.answers.get(timeout=0.1)
            except queue.Empty:
                continue
            if not job:  # acknowledged: ask for the next job
                self._ready(node, time.perf_counter())
                continue
            fitness = self.jitter.uniform(0, 100)
            policy = untrained_policy(Genome.model_validate(genome), "ft")
            report = dict(self.report, agent=child, job=job, node=node, genome=genome,
                          fitness=fitness, env_steps=min(2, budget), checkpoint=policy)  # fmt: skip
            with self.lock:
                self.unacked[job] = (node, time.perf_counter())
            self._put(self.keys.fitness(node, child), msgpack.packb(report, use_bin_type=True))

    def _on_ack(self, sample: zenoh.Sample) -> None:
        """Acknowledged (or rejected, counted): idle again (a real worker also waits for the
        Ack, then asks for work; it re-sends its report every second until then, which this
        generator does not)."""
        ack = msgpack.unpackb(sample.payload.to_bytes())
        now = time.perf_counter()
        with self.lock:
            node, sent = self.unacked.pop(ack["job"], (None, now))
            if ack["type"] == "Reject":
                self.rejected[ack["reason"][:80]] += 1
            elif node is not None:
                self.acked.append((now, now - sent))
                self.ack_wait[node] = now - sent
        if node is not None:
            self.answers.put((node, "", "", None, 0))

    def _resend(self) -> None:
        """Idle simulated workers repeat WorkerReady as real ones do (`ready_wait`)."""
        while not self.stop.is_set():
            time.sleep(0.2)
            now = time.perf_counter()
            with self.lock:
                stale = [n for n, (t, asks) in self.last_ready.items()
                         if now - t >= ready_wait(asks)]  # fmt: skip
            for node in stale:
                self._ready(node, now)

    def window(self, start: float, end: float) -> dict[str, object]:
        with self.lock:
            inside = [(t, lat, part) for t, lat, _, part in self.received if start <= t < end]
            acks = [wait for t, wait in self.acked if start <= t < end]
            repeated, self.repeated = self.repeated, 0
            rejected, self.rejected = dict(self.rejected), Counter()
            cancelled, self.cancelled = self.cancelled, 0
        latencies = [lat for _, lat, _ in inside]
        parts = [part for _, _, part in inside if part is not None]
        return {
            "assignments_per_s": round(len(inside) / (end - start), 1),
            "latency_p50_ms": _ms(_percentile(latencies, 50)),
            "latency_p99_ms": _ms(_percentile(latencies, 99)),
            "latency_max_ms": _ms(max(latencies, default=None)),
            # from the ask until the coordinator put its job on the bus (the job's timestamp):
            # the latency less the generator's own wait to take the job (on one small machine,
            # for the cores and its interpreter lock, which a remote worker does not share)
            "coordinator_latency_p50_ms": _ms(_percentile(parts, 50)),
            "coordinator_latency_p99_ms": _ms(_percentile(parts, 99)),
            "coordinator_latency_max_ms": _ms(max(parts, default=None)),
            # a report's wait for its Ack: its journal entry and checkpoint file on the disk
            "ack_p50_ms": _ms(_percentile(acks, 50)),
            "ack_p99_ms": _ms(_percentile(acks, 99)),
            "assignments": len(inside),
            "jobs_sent_again": repeated,  # a worker that re-sent WorkerReady before its job came
            "reports_rejected": rejected,  # reason -> count; none expected
            "jobs_cancelled": cancelled,  # none expected
        }

    def tournaments_started(self) -> bool:
        with self.lock:
            return any(child.startswith("c") for _, _, child, _ in self.received[-50:])


def _peer_config(endpoint: str) -> zenoh.Config:
    from derl.nodes.runtime.bus import zenoh_config

    return zenoh_config(ZenohOptions(connect=(endpoint,)))


def bench_assignments(workers: int, duration: float, work: Path) -> dict[str, object]:
    from derl.nodes.runtime.processes import spawn_derl, stop_all

    run = f"bench-{workers}"
    run_dir = work / run
    seed_run_dir(run_dir, load_profile("paper").population)
    profile = work / f"{run}.yaml"
    profile.write_text(yaml.safe_dump(SCALE_PROFILE))
    zenoh_file = work / f"{run}-zenoh.json5"
    zenoh_file.write_text(json.dumps(TIMESTAMPING))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    log = work / f"{run}-coordinator.log"
    coordinator = spawn_derl(
        ["coordinator", "--run", run, "--profile", str(profile), "--run-dir", str(run_dir),
         "--listen", endpoint, "--zenoh-config", str(zenoh_file)], log,
    )  # fmt: skip
    result: dict[str, object] = {"workers": workers}
    try:
        wait_until(lambda: "replayed" in log.read_text(), 60, "the coordinator to start")
        generator = LoadGenerator(run, endpoint, workers)
        try:
            generator.start()
            started = time.perf_counter()
            wait_until(generator.tournaments_started, 120, "the initial population to be born")
            result["initial_population_born_s"] = round(time.perf_counter() - started, 1)
            saturated = _phase(generator, coordinator.pid, 0.0, duration)
            result["saturated"] = saturated
            capacity = max(float(saturated["assignments_per_s"]), 1.0)
            before = 0.0  # the previous phase's cycle
            for name, rate in (("half_capacity", capacity / 2), ("paced_1000_per_s", GOAL_RATE)):
                cycle_s = workers / rate
                # the window opens once every job given at the previous pace is answered and
                # the new pace has run a whole cycle (one lasts up to 1.5 times cycle_s): while
                # both paces' jobs end together the offered rate overshoots the new one (from
                # half capacity to 1,000/s, measured: the p99 of a window opened 1.5 cycles
                # after the change was 46-65 ms, every job over 50 ms in its first half second)
                phase = _phase(generator, coordinator.pid, cycle_s, duration,
                               settle=1.5 * (before + cycle_s))  # fmt: skip
                before = cycle_s
                result[name] = {"offered_per_s": round(rate, 1), "cycle_s": round(cycle_s, 3),
                                **phase}  # fmt: skip
        finally:
            generator.close()
    finally:
        stop_all([coordinator], timeout=10)
    return result


def _phase(
    generator: LoadGenerator, pid: int, cycle_s: float, duration: float, settle: float = 1.0
) -> dict[str, object]:
    generator.cycle_s = cycle_s
    time.sleep(min(settle, MAX_SETTLE_S))
    own = os.getpid()
    cpu0, generator0, start = _cpu_s(pid), _cpu_s(own), time.perf_counter()
    time.sleep(duration)
    end = time.perf_counter()
    out = generator.window(start, end)
    out["coordinator_cpu_share"] = round((_cpu_s(pid) - cpu0) / (end - start), 2)
    # the load generator shares the machine's cores with the coordinator
    out["load_generator_cpu_share"] = round((_cpu_s(own) - generator0) / (end - start), 2)
    # every simulated worker went through a few jobs before the window (Little's law: one
    # cycle lasts W / rate): else the latencies still hold the start's queue; and the phase
    # settled as long as its paces need (not at 10,000 workers: their cycles are too long)
    rate = max(float(out["assignments_per_s"]), 1e-9)
    cycles = start - generator.started >= 2 * len(generator.nodes) / rate
    out["steady_state"] = cycles and settle <= MAX_SETTLE_S
    return out


# --- 2. the coordinator's own cost ---------------------------------------------------------


class _NoBus:
    """Stands in for the bus when the coordinator's handlers are driven in-process."""

    def __init__(self) -> None:
        self.rejected: Counter[str] = Counter()

    def publish(self, msg: object, data: bytes | None = None) -> None:
        pass


def _open_coordinator(run: str, run_dir: Path, config: EvolutionConfig, publisher=None):
    """A run's coordinator, as `derl coordinator` makes it (without its bus: its replies go to
    `publisher`)."""
    from derl.nodes.coordinator.node import Coordinator
    from derl.nodes.coordinator.run.rules import EvolutionRules

    return Coordinator(run, run_dir, EvolutionRules(run, run_dir, config), publisher=publisher)


def _coordinator(run: str, run_dir: Path, config: EvolutionConfig):
    seed_run_dir(run_dir, config.population)
    return _open_coordinator(run, run_dir, config, publisher=_NoBus())


class Driver:
    """Simulated workers driving the coordinator's own handlers in this process (no bus)."""

    def __init__(self, coordinator, rng: random.Random, curve_points: int = 100) -> None:
        self.coordinator, self.rng, self.curve_points = coordinator, rng, curve_points
        self.busy: deque[TrainJob] = deque()
        self.idle: list[str] = []
        self.workers = 0
        self.retried = False

    def add_workers(self, count: int) -> None:
        self.idle += [f"w{k:05d}" for k in range(self.workers, self.workers + count)]
        self.workers += count
        self.retried = False

    def _ready(self, node: str) -> TrainJob | None:
        coordinator, state = self.coordinator, self.coordinator.state
        ready = WorkerReady(run=coordinator.run, node=node, role="trainer", host="h", pid=1)
        if node not in coordinator.tokens:  # a worker holds a liveliness token
            coordinator.take(Liveliness("trainer", node, True))
        coordinator.dispatch(ready)
        coordinator.ledger.flush()  # as the serve loop does after each group (here: each message)
        coordinator._publish_released()
        job = state.job_of(node)
        return None if job is None else job.order

    def run(self, births: int, profiler: cProfile.Profile | None = None) -> list[float]:
        """`births` more births; the CPU seconds of this thread each assignment took (decoding a
        fitness report, handling it and the worker's next WorkerReady, breeding its child
        included, each one a group of its own: the most journal flushes; the checkpoint files
        are written by the coordinator's other thread)."""
        coordinator = self.coordinator
        times: list[float] = []
        target = coordinator.rules.born + births
        while coordinator.rules.born < target:
            tournaments = bool(coordinator.state.evolution.born) and not coordinator.state.waiting
            if not self.busy or (self.idle and tournaments and not self.retried):
                self.retried = tournaments  # idle workers ask again once tournaments start
                retry, self.idle = self.idle, []
                for node in retry:
                    job = self._ready(node)
                    self.busy.append(job) if job else self.idle.append(node)
                if not self.busy:
                    raise RuntimeError("the coordinator gives no work")
                continue
            job = self.busy.popleft()
            fitness = self.rng.uniform(0, 100)
            data = encode(fake_report(coordinator.run, job, fitness, self.curve_points))
            if profiler is not None:
                profiler.enable()
            start = time.thread_time()
            coordinator.dispatch(decode(data))  # decoding is the coordinator's part
            coordinator.ledger.flush()
            coordinator._publish_released()
            following = self._ready(job.node)
            times.append(time.thread_time() - start)
            if profiler is not None:
                profiler.disable()
            self.busy.append(following) if following else self.idle.append(job.node)
        return times


BREAKDOWN = {  # label: (file, function) whose cumulative time is reported
    "tournament (drawing contestants)": ("evolution/evolution.py", "tournament"),
    "breeding (mutation and validity check)": ("evolution/evolution.py", "breed"),
    "repeat lookup (body hash)": ("evolution/evolution.py", "repeat"),
    "journal writes": ("nodes/journal/segments.py", "write"),
    "journal flushes (the fsync is on the outbox thread)": ("nodes/journal/segments.py", "flush"),
    "checkpoint hand-off (a thread writes the file)": ("nodes/runtime/checkpoints.py", "save"),
    "messages built (pydantic validation)": ("pydantic/main.py", "__init__"),
    "encode (msgpack)": ("messages/codec.py", "encode"),
    "apply (the state's fold)": ("nodes/journal/history.py", "apply"),
    "job_of (per WorkerReady)": ("nodes/coordinator/jobs.py", "job_of"),
    "wants_tournament": ("nodes/coordinator/run/state.py", "wants_tournament"),
}


def bench_coordinator_profile(work: Path, in_flight: list[int], births: int) -> list[dict]:
    config = load_profile("paper", WINDOW).model_copy(
        update={"total": 10_000_000, "lease_s": 3600.0}
    )
    out = []
    for k in in_flight:
        coordinator = _coordinator(f"prof-{k}", work / f"prof-{k}", config)
        driver = Driver(coordinator, random.Random(0))
        driver.add_workers(k)
        driver.run(config.population)  # the initial bodies, then K tournament jobs in flight
        driver.run(20)
        assert len(coordinator.state.jobs) == k, len(coordinator.state.jobs)
        born = len(coordinator.state.births)
        times = driver.run(births)
        window = coordinator.state.births[born:]
        repeats = sum(1 for birth in window if birth.repeat_of) / len(window)
        profiler = cProfile.Profile(time.thread_time)
        profiled = driver.run(births, profiler)
        coordinator.close()
        stats = pstats.Stats(profiler, stream=io.StringIO()).stats
        total = sum(profiled)
        breakdown = {}
        for label, (file, name) in BREAKDOWN.items():
            # the outermost of same-named functions (Journal.write calls JournalWriter.write)
            cumulative = max((v[3] for (f, _, n), v in stats.items()
                              if f.endswith(file) and n == name), default=0.0)  # fmt: skip
            breakdown[label] = round(cumulative / total, 3)
        top = []
        for (file, line, name), (_, calls, tottime, _cumtime, _) in sorted(
            stats.items(), key=lambda item: item[1][2], reverse=True
        )[:6]:
            top.append({"function": f"{Path(file).name}:{line}({name})", "calls": calls,
                        "self_share": round(tottime / total, 3)})  # fmt: skip
        out.append({
            "in_flight": k,
            "assignments": len(times),
            "births_as_repeats_share": round(repeats, 3),
            "ms_per_assignment_p50": _ms(statistics.median(times)),
            "ms_per_assignment_mean": _ms(statistics.fmean(times)),
            "assignments_per_s_ceiling": round(len(times) / sum(times), 1),
            "share_of_time_under_cprofile": breakdown,
            "top_self_time": top,
        })  # fmt: skip
    return out


def _rss_mb() -> float:
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def bench_memory(work: Path, births: int = 4000, every: int = 500) -> dict[str, object]:
    config = load_profile("paper", WINDOW).model_copy(
        update={"population": 8, "total": 10_000_000, "lease_s": 3600.0}
    )
    coordinator = _coordinator("memory", work / "memory", config)
    driver = Driver(coordinator, random.Random(0), curve_points=PAPER_CURVE_POINTS)
    driver.add_workers(2)
    samples = []
    try:
        while len(coordinator.state.births) < births:
            driver.run(every)
            gc.collect()
            samples.append({"births": len(coordinator.state.births), "rss_mb": round(_rss_mb(), 1)})
    finally:
        coordinator.close()
    first, last = samples[0], samples[-1]
    grown = last["births"] - first["births"]
    return {
        "samples": samples,
        "rss_kb_per_birth": round((last["rss_mb"] - first["rss_mb"]) * 1024 / grown, 1),
    }


# --- 3. the journal ------------------------------------------------------------------------


def bench_journal(work: Path, messages: int = 8000) -> dict[str, object]:
    from derl.nodes.journal.segments import JournalWriter, read_segment

    run = "bench-journal"
    genome = bodies()[0]
    ppo = load_profile("paper").training_ppo()
    mix = []
    for k in range(messages // 4):
        job = TrainJob(run=run, job=f"c{k:05d}.1", agent=f"c{k:05d}", node=f"w{k % 300}",
                       genome=genome, task="ft", ppo=ppo, parent="i0001", mutation="gear",
                       lease_s=60.0)  # fmt: skip
        mix += [
            Tournament(run=run, agent=job.agent, contestants=("i0001",) * 4,
                       fitness=(1.0,) * 4, parent="i0001", mutation_seed=k, iteration=k),
            job, fake_report(run, job, 1.0),
            _ack(run, job),
        ]  # fmt: skip
    rates = {}
    for group in (1, 4, 16):  # messages per flush: 1 = each on its own, 4 = one assignment's
        path = work / f"journal-bench-{group}.mcap"
        start = time.perf_counter()
        with JournalWriter(path) as writer:
            for k, msg in enumerate(mix, 1):
                writer.write(msg, flush=k % group == 0)
        rates[group] = len(mix) / (time.perf_counter() - start)
    path = work / "journal-bench-1.mcap"  # sizes and replay: a chunk per message, the most
    start = time.perf_counter()
    count = sum(1 for _ in read_segment(path))
    read = time.perf_counter() - start
    size = path.stat().st_size
    return {
        "messages": len(mix),
        "write_messages_per_s": round(rates[1]),
        "write_mb_per_s": round(size * rates[1] / len(mix) / 1e6, 1),
        "bytes_per_message": round(size / len(mix)),
        "write_messages_per_s_flushed_per_4": round(rates[4]),
        "write_messages_per_s_flushed_per_16": round(rates[16]),
        "replay_messages_per_s": round(count / read),
        "flush": "every message or group (crash-safe: a SIGKILL loses at most the message or "
        "group being written, which was not published yet)",
    }


def _ack(run: str, job: TrainJob):
    from derl.messages import Ack

    return Ack(run=run, of="FitnessReport", job=job.job, agent=job.agent, node=job.node)


# --- 4. recovery ---------------------------------------------------------------------------


def bench_recovery(work: Path, bodies_total: int = 4000, repeats: int = 3) -> dict[str, object]:
    """A paper-sized journal (`bodies_total` births, the initial P included, 64 jobs in flight
    at the end), then (a) the coordinator in this process: the replay, and
    (b) a real `derl coordinator` process started on it: the time from its start until it
    serves (a job sent again to a worker that held one when it stopped, the first RunStatus),
    `repeats` times each."""
    from derl.nodes.journal.segments import read_segment, segments

    config = load_profile("paper", WINDOW).model_copy(update={"total": bodies_total + 64})
    run_dir = work / "recovery"
    start = time.perf_counter()
    coordinator = _coordinator("recovery", run_dir, config)
    driver = Driver(coordinator, random.Random(1))
    driver.add_workers(64)
    driver.run(bodies_total)
    coordinator.close()
    made = time.perf_counter() - start
    holder = driver.busy[0]
    del coordinator, driver  # the run made: its heap would slow this process's collections
    gc.collect()
    journal = segments(run_dir)[0]
    kinds = Counter(msg.type for msg in read_segment(journal))
    times, cpu = [], []
    for _ in range(repeats):
        start, cpu0 = time.perf_counter(), time.process_time()
        restarted = _open_coordinator("recovery", run_dir, config)
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - cpu0)
        restarted.close()
        assert restarted.rules.born == bodies_total, restarted.rules.born
        segments(run_dir)[-1].unlink()  # the empty segment each start opens
    serving = [_time_to_serving(work, run_dir, holder) for _ in range(repeats)]
    return {
        "bodies": bodies_total,
        "journal_messages": restarted.ledger.replayed,
        "journal_births": kinds["Birth"],
        "journal_tournaments": kinds["Tournament"],
        "journal_mb": round(journal.stat().st_size / 1e6, 1),
        "recovery_s_median": round(statistics.median(times), 2),
        "recovery_s_all": [round(t, 2) for t in times],
        "recovery_cpu_s_median": round(statistics.median(cpu), 2),
        "coordinator_process_to_status_s_median": round(
            statistics.median(s["status_s"] for s in serving), 2
        ),
        "coordinator_process_to_job_s_median": round(
            statistics.median(s["job_s"] for s in serving), 2
        ),
        "coordinator_process_cpu_to_job_s_median": round(
            statistics.median(s["job_cpu_s"] for s in serving), 2
        ),
        "coordinator_process_all": serving,
        "journal_made_in_s": round(made, 1),
    }


def _time_to_serving(work: Path, run_dir: Path, holder: TrainJob) -> dict[str, float]:
    """Start `derl coordinator` on `run_dir` and time (from the start of its process) the first
    RunStatus heard and the job it sends again to `holder`'s node, which asks for work every
    50 ms as a worker does after a coordinator restart."""
    from derl.nodes.journal.segments import segments
    from derl.nodes.runtime.processes import spawn_derl, stop_all

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    heard: dict[str, float] = {}
    cpu: dict[str, float] = {}  # the coordinator process's CPU s when it served
    # this session listens and the coordinator connects: connecting first, this session would
    # wait out Zenoh's backoff between attempts (measured: the job always came at 10.5 s)
    with open_session(ZenohOptions(listen=(endpoint,))) as session:
        bus = Bus(session, holder.run)

        def on(msg: MessageBase) -> None:
            if msg.type not in heard:
                heard[msg.type] = time.perf_counter()
                cpu[msg.type] = _cpu_s(coordinator.pid)

        bus.subscribe(bus.keys.status(), on, (RunStatus,))
        bus.subscribe(bus.keys.job(holder.node), on, (TrainJob,))
        ready = WorkerReady(run=holder.run, node=holder.node, role="trainer", host="h", pid=1)
        segments_before = len(segments(run_dir))
        start = time.perf_counter()
        coordinator = spawn_derl(
            ["coordinator", "--run", holder.run, "--profile", "paper", "--run-dir",
             str(run_dir), "--connect", endpoint], work / "recovery-coordinator.log",
        )  # fmt: skip
        try:
            deadline = start + 300
            while len(heard) < 2 and time.perf_counter() < deadline:
                bus.publish(ready)
                time.sleep(0.05)
        finally:
            stop_all([coordinator], timeout=30)
    for segment in segments(run_dir)[segments_before:]:
        segment.unlink()  # the start's own segment: every repeat replays the same journal
    if len(heard) < 2:
        raise TimeoutError(f"the coordinator did not serve: {sorted(heard)} heard")
    return {"status_s": round(heard["RunStatus"] - start, 2),
            "job_s": round(heard["TrainJob"] - start, 2),
            "job_cpu_s": round(cpu["TrainJob"], 2)}  # fmt: skip


# --- 5. the bus's share of a trainer's wall time -------------------------------------------


def hub(endpoint: str, run: str, seconds: float) -> None:
    """The coordinator's side for `bus_share`, in its own process: listens, decodes everything
    of the run (as the coordinator and a recorder would), publishes RunStatus at 1 Hz."""
    with open_session(ZenohOptions(listen=(endpoint,))) as session:
        bus = Bus(session, run)
        received: Counter[str] = Counter()
        bus.subscribe(f"derl/{run}/**", lambda m: received.update([m.type]))
        status = RunStatus(run=run, born=10, target=4000, in_flight=288, workers_alive=288)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not received["Ack"]:  # an Ack says: stop
            bus.publish(status)
            time.sleep(1.0)
        print(json.dumps(dict(received)), flush=True)


def bench_bus_share(steps: int, samples: int = 200) -> dict[str, object]:
    import subprocess

    from derl.lifetime import learn, ppo_config
    from derl.messages import Ack

    run, node = "bench-share", "trainer-0"
    genome = bodies()[1]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    coordinator = subprocess.Popen(
        [sys.executable, __file__, "--hub", endpoint, run], stdout=subprocess.PIPE, text=True
    )
    try:
        time.sleep(3.0)  # the hub's imports
        with open_session(ZenohOptions(connect=(endpoint,))) as session:
            bus = Bus(session, run)
            statuses: list[RunStatus] = []
            bus.subscribe(bus.keys.status(), statuses.append, (RunStatus,))  # as a worker does
            bus.subscribe(bus.keys.job(node), lambda m: None)
            bus.subscribe(bus.keys.ack(node), lambda m: None)
            wait_until(lambda: statuses, 30, "the hub's status")
            # (1) the open session's own threads (keep-alives, the 1 Hz status): the CPU this
            # process uses while its main thread sleeps
            cpu0, idle0 = time.process_time(), time.perf_counter()
            time.sleep(5.0)
            idle_cpu = (time.process_time() - cpu0) / (time.perf_counter() - idle0)
            costs: dict[str, list[float]] = {"WorkerReady": [], "TrainProgress": [],
                                             "FitnessReport": []}  # fmt: skip

            def timed(msg) -> None:
                start = time.perf_counter()
                bus.publish(msg)
                costs[msg.type].append(time.perf_counter() - start)

            # (2) a real training with the worker's publishing cadence
            timed(WorkerReady(run=run, node=node, role="trainer", host="h", pid=os.getpid()))
            last = 0.0

            def progress(p) -> None:  # as nodes.worker.node: at most one TrainProgress a second
                nonlocal last
                now = time.monotonic()
                if now - last >= 1.0 or p.iteration == p.iterations:
                    last = now
                    message = TrainProgress(
                        run=run, agent="c00001", job="c00001.1", node=node,
                        env_steps=p.env_steps, total_steps=steps, recent_return=p.recent_return,
                        steps_per_s=p.steps_per_second,
                    )  # fmt: skip
                    timed(message)

            config = ppo_config("ft", steps, 1409)
            wall0 = time.perf_counter()
            summary, result = learn(genome, "ft", config, progress)
            wall = time.perf_counter() - wall0
            checkpoint = result.checkpoint.to_bytes()
            job = TrainJob(run=run, job="c00001.1", agent="c00001", node=node, genome=genome,
                           task="ft", ppo=config, lease_s=60.0)  # fmt: skip
            report = fake_report(run, job, summary.fitness)
            report = report.model_copy(update={"checkpoint": checkpoint})
            timed(report)
            in_training = {k: list(v) for k, v in costs.items()}
            # (3) publish costs on a quiet process, many samples
            quiet: dict[str, list[float]] = {}
            for msg, count in ((report, 20), (TrainProgress(
                    run=run, agent="c00001", job="c00001.1", node=node, env_steps=1,
                    total_steps=steps, recent_return=1.0, steps_per_s=1.0), samples)):  # fmt: skip
                for _ in range(count):
                    start = time.perf_counter()
                    bus.publish(msg)
                    quiet.setdefault(msg.type, []).append(time.perf_counter() - start)
                    time.sleep(0.005)
            bus.publish(Ack(run=run, of="FitnessReport", job=job.job, agent=job.agent, node=node))
        received = json.loads(coordinator.communicate(timeout=30)[0].strip().splitlines()[-1])
    finally:
        if coordinator.poll() is None:
            coordinator.kill()
            coordinator.wait()
    publish_s = sum(sum(v) for v in in_training.values())
    speed = summary.steps_per_second
    paper_wall = 5_000_000 / speed
    progress_s = statistics.median(quiet["TrainProgress"])
    report_s = statistics.median(quiet["FitnessReport"])
    # per second of training: one TrainProgress; once: WorkerReady and the report
    paper_publish = progress_s * paper_wall + report_s + max(in_training["WorkerReady"])
    return {
        "training": {
            "steps": steps,
            "num_envs": config.num_envs,
            "wall_s": round(wall, 1),
            "steps_per_s": round(speed),
        },
        "publishes_in_training": {k: len(v) for k, v in in_training.items()},
        "publish_us_in_training": {
            k: round(statistics.fmean(v) * 1e6, 1) for k, v in in_training.items()
        },
        "publish_us_median_quiet": {
            k: round(statistics.median(v) * 1e6, 1) for k, v in quiet.items()
        },
        "checkpoint_bytes": len(checkpoint),
        "received_by_coordinator_side": received,
        "session_threads_cpu_s_per_s": round(idle_cpu, 5),
        "measured": {
            "publishing_share": round(publish_s / wall, 5),
            "upper_bound_share": round((publish_s + idle_cpu * wall) / wall, 5),
        },
        "paper_training": {
            "steps": 5_000_000,
            "wall_s_at_this_speed": round(paper_wall),
            "publishing_share": round(paper_publish / paper_wall, 5),
            "upper_bound_share": round((paper_publish + idle_cpu * paper_wall) / paper_wall, 5),
        },
        "method": "a real training in this process with the worker's publishing (WorkerReady, "
        "one TrainProgress a second, the FitnessReport with the real checkpoint) over a real "
        "Zenoh session to a coordinator-side process that decodes everything and sends the 1 Hz "
        "RunStatus. publishing_share: the wall time the training thread spent in those "
        "publishes. upper_bound_share: plus all CPU the session's own threads use (measured "
        "while the main thread sleeps), as if it all stalled the training (it runs on other "
        "threads). Paper length: the same per-second costs (quiet medians) over 5M steps at "
        "the measured speed.",
    }


# --- main ----------------------------------------------------------------------------------


def file_creation(work: Path, files: int = 500) -> dict[str, object]:
    """The cost of creating a file in the runs' folder: the coordinator creates one per birth
    (its checkpoint, in `checkpoint_writer`'s process), so at a thousand births a second a
    folder whose file system takes a millisecond of CPU per file costs a core. Measured on one
    machine: 20-27 µs, and ~1 ms for minutes after many files were deleted nearby (an ext4
    without a journal does not reuse recently deleted inodes, and walks past each of them)."""
    folder = work / "file-creation"
    folder.mkdir()
    wall, cpu = time.perf_counter(), time.process_time()
    for k in range(files):
        os.close(os.open(folder / f"{k}.tmp", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644))
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    # the files stay until the end: deleted now, they would slow every file the runs create
    out: dict[str, object] = {"file_create_us": round(wall / files * 1e6, 1),
                              "file_create_cpu_us": round(cpu / files * 1e6, 1)}  # fmt: skip
    if wall / files > SLOW_FILE_S:
        out["warning"] = (
            "creating a file is slow here: the checkpoint writer will take CPU from the "
            "coordinator (docs/performance.md; try another --work)"
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", default="100,1000,10000", help="simulated worker counts")
    parser.add_argument("--duration", type=float, default=8.0, help="seconds per measurement")
    parser.add_argument("--profile-births", type=int, default=200)
    parser.add_argument(
        "--in-flight",
        default="1,1000,10000",
        help="coordinator_profile's jobs in flight (comma-separated)",
    )
    parser.add_argument("--train-steps", type=int, default=8 * 4096)
    parser.add_argument("--work", help="folder for the runs' files (default: a temp folder)")
    parser.add_argument("--keep", action="store_true", help="keep the runs' files")
    parser.add_argument("--skip-train", action="store_true", help="no bus-share training")
    parser.add_argument("--only", help="comma-separated sections (assignments, coordinator_"
                        "profile, journal, recovery, bus_share, memory)")  # fmt: skip
    parser.add_argument("--hub", nargs=2, metavar=("ENDPOINT", "RUN"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.hub:
        return hub(*args.hub, seconds=600)
    os.environ.setdefault("MUJOCO_GL", "egl")
    import logging

    logging.basicConfig(level=logging.WARNING)
    only = set(args.only.split(",")) if args.only else None
    work = Path(tempfile.mkdtemp(prefix="derl-bench-bus-", dir=args.work))
    out: dict[str, object] = {"cpus": os.cpu_count(), "goals": {
        "assignments_per_s_at_1000_workers": ">= 1000 with p99 < 50 ms",
        "recovery_4000_bodies_s": "< 3", "bus_share_of_trainer_wall_time": "< 0.005"}}  # fmt: skip
    out["work"] = {"folder": str(work), **file_creation(work)}
    try:
        if only is None or "journal" in only:
            out["journal"] = bench_journal(work)
        if only is None or "recovery" in only:
            out["recovery"] = bench_recovery(work)
        if only is None or "coordinator_profile" in only:
            out["coordinator_profile"] = bench_coordinator_profile(
                work, [int(k) for k in args.in_flight.split(",")], args.profile_births
            )
        if only is None or "assignments" in only:
            out["assignments"] = [
                bench_assignments(int(w), args.duration, work) for w in args.workers.split(",")
            ]
        if only is None or "memory" in only:
            out["memory"] = bench_memory(work)
        if (only is None or "bus_share" in only) and not args.skip_train:
            out["bus_share"] = bench_bus_share(args.train_steps)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
