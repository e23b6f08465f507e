"""A run on a shared network with the identities `derl certs` writes for a launch file: mutual
TLS, one certificate per node (common name = node id) and access control under which a node may
publish only on its own keys.

Shown with real node processes on loopback (multicast off), started from the launch file's own
commands:
- the coordinator and a trainer run a tiny run to its end over TLS only;
- a client with no certificate, with a certificate from another CA, or speaking plain TCP cannot
  connect; a certificate from the run's CA with a name that is no node's sees nothing and
  delivers nothing (default deny);
- another node's certificate cannot publish on the trainer's keys (not delivered to anyone), nor
  give jobs; on its own keys it is heard, and its reports for the trainer's job, or naming the
  trainer on its own key, are rejected by the coordinator; a restarted node (``<id>.r1``) keeps
  its keys;
- the monitor's certificate sees the whole run and can query the births, but nothing it
  publishes is delivered.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
import zenoh
from cryptography.hazmat.primitives.serialization import load_pem_private_key
from cryptography.x509 import load_pem_x509_certificate
from nodes_fixtures import (
    REPO,
    LocalRun,
    Processes,
    assert_born_once,
    derl_argv,
    free_port,
    observe,
    run_id,
    write_profile,
)

from derl.evolution import breed
from derl.messages import (
    Birth,
    FitnessReport,
    MessageBase,
    Reject,
    Rejection,
    RunStatus,
    TrainJob,
    decode,
    encode,
)
from derl.messages.examples import examples
from derl.nodes.journal.segments import replay
from derl.nodes.launch.commands import build_commands
from derl.nodes.launch.identities import MONITOR, issue, make_ca
from derl.nodes.launch.model import load
from derl.nodes.runtime.bus import Bus, ZenohOptions, zenoh_config
from derl.nodes.testing.waiting import wait_until

FORGED_FITNESS = -4242.0


def _derl(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(derl_argv(*args), capture_output=True, text=True, cwd=REPO, timeout=60)


def _launch_file(tmp: Path, port: int) -> Path:
    """One host: the coordinator (the mesh's seed) and two trainer slots, over TLS."""
    seed = f"tls/127.0.0.1:{port}"
    data = {
        "run": run_id(),
        "run_dir": str(tmp / "run"),
        "profile": str(write_profile(tmp / "profile.yaml", total=3, train_steps=16384)),
        "certs": str(tmp / "certs"),
        "topology": {"kind": "peer_mesh", "seed": seed},
        "hosts": [{"name": "h", "listen": seed,
                   "nodes": [{"role": "coordinator"}, {"role": "trainer", "count": 2}]}],
    }  # fmt: skip
    path = tmp / "launch.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _client_config(certs: Path, folder: Path | None, name: str) -> Path:
    """The monitor's client config with another identity's certificate (None: no certificate)."""
    config = json.loads((certs / MONITOR / "zenoh.json5").read_text())
    tls = config["transport"]["link"]["tls"]
    for end in ("connect", "listen"):
        if folder is None:
            del tls[f"{end}_certificate"], tls[f"{end}_private_key"]
        else:
            tls[f"{end}_certificate"] = str(folder / "node.pem")
            tls[f"{end}_private_key"] = str(folder / "node.key")
    path = certs.parent / f"client-{name}.json5"
    path.write_text(json.dumps(config))
    return path


def _open(options: ZenohOptions, timeout_ms: int = 3000) -> zenoh.Session:
    config = zenoh_config(options)
    if options.mode == "client":
        config.insert_json5("connect/timeout_ms", json.dumps(timeout_ms))
    return zenoh.open(config)


class Tap:
    """A session of the test that records every message of the run it can see."""

    def __init__(self, session: zenoh.Session, run: str) -> None:
        self.session = session
        self.bus = Bus(session, run)
        self.seen: list[MessageBase] = []
        self.jobs: queue.Queue[TrainJob] = queue.Queue()

        def on_sample(sample: zenoh.Sample) -> None:
            message = decode(sample.payload.to_bytes())
            self.seen.append(message)
            if isinstance(message, TrainJob):
                self.jobs.put(message)

        self.subscriber = session.declare_subscriber(  # what others publish, not its own
            f"derl/{run}/**", on_sample, allowed_origin=zenoh.Locality.REMOTE
        )

    def of(self, kind: type[MessageBase]) -> list:
        return [m for m in self.seen if isinstance(m, kind)]


@pytest.fixture
def sessions() -> Iterator[list[zenoh.Session]]:
    opened: list[zenoh.Session] = []
    try:
        yield opened
    finally:
        for session in opened:
            session.close()


def _report(run: str, job: str, child: str, node: str) -> FitnessReport:
    template = next(m for m in examples(run, 0) if isinstance(m, FitnessReport))
    update = {"job": job, "agent": child, "node": node, "fitness": FORGED_FITNESS}
    return template.model_copy(update=update)


def test_certs_command_writes_one_identity_per_node(tmp_path: Path) -> None:
    file = _launch_file(tmp_path, 7447)
    result = _derl("certs", str(file))
    assert result.returncode == 0, result.stderr
    certs = tmp_path / "certs"
    for name in ("h-coordinator-0", "h-trainer-0", "h-trainer-1", MONITOR):
        pem = load_pem_x509_certificate((certs / name / "node.pem").read_bytes())
        assert pem.subject.rfc4514_string() == f"CN={name}"
        assert (certs / name / "node.key").stat().st_mode & 0o077 == 0
        config = json.loads((certs / name / "zenoh.json5").read_text())
        assert config["access_control"]["default_permission"] == "deny"
    launch = load(file)
    for command in build_commands(launch):  # each node takes its own identity
        args = command.derl_args()
        assert args[args.index("--zenoh-config") + 1] == str(certs / command.name / "zenoh.json5")
    again = _derl("certs", str(file))  # never overwrites a CA (every certificate would change)
    assert again.returncode == 1 and "already holds a CA" in again.stderr


def test_tls_and_per_node_access_control(tmp_path: Path, sessions: list) -> None:
    port = free_port(span=3)
    file = _launch_file(tmp_path, port)
    assert _derl("certs", str(file)).returncode == 0
    launch, certs = load(file), tmp_path / "certs"
    run, run_dir, seed = launch.run, launch.run_dir, launch.topology.seed
    # identities that are no node's: a name the run's CA signed, a trainer's name from another CA
    ca_key = load_pem_private_key((certs / "ca.key").read_bytes(), None)
    ca = load_pem_x509_certificate((certs / "ca.pem").read_bytes())
    issue(ca_key, ca, "derl-stranger", ["127.0.0.1"], tmp_path / "stranger")
    other_key, other = make_ca(tmp_path, "another CA")
    issue(other_key, other, "h-trainer-0", ["127.0.0.1"], tmp_path / "impostor")

    commands = {c.name: c for c in build_commands(launch)}
    processes = Processes(tmp_path / "logs")
    try:
        processes.start("coordinator", derl_argv(*commands["h-coordinator-0"].derl_args()))
        wait_until(lambda: "replayed" in processes.log("coordinator"), 60, "the coordinator")

        def client(config: Path | None, endpoint: str = seed) -> ZenohOptions:
            return ZenohOptions(mode="client", connect=(endpoint,), config_file=config)

        refused = {
            "no certificate": client(_client_config(certs, None, "none")),
            "another CA": client(_client_config(certs, tmp_path / "impostor", "impostor")),
            "plain tcp": client(None, f"tcp/127.0.0.1:{port}"),
        }
        for why, options in refused.items():
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                _open(options).close()
                pytest.fail(f"a client with {why} connected")

        def tap(config: Path) -> Tap:
            sessions.append(_open(client(config)))
            return Tap(sessions[-1], run)

        monitor = tap(certs / MONITOR / "zenoh.json5")
        stranger = tap(_client_config(certs, tmp_path / "stranger", "stranger"))
        other = tap(_client_config(certs, certs / "h-trainer-1", "trainer-1"))  # another node
        processes.start("trainer", derl_argv(*commands["h-trainer-0"].derl_args()))

        job = monitor.jobs.get(timeout=90)
        trainer = job.node
        assert trainer == "h-trainer-0"
        # on the trainer's own key, under its name: the access control drops it at once
        other.bus.publish(_report(run, job.job, job.agent, trainer))
        other.bus.publish(job.model_copy(update={"job": "forged-job", "node": trainer}))
        # on its own keys: heard, and the coordinator rejects it (not its job; not its name)
        other.bus.publish(_report(run, job.job, job.agent, "h-trainer-1"))
        own_key = other.bus.keys.fitness("h-trainer-1", job.agent)
        other.session.put(own_key, encode(_report(run, job.job, job.agent, trainer)))
        other.bus.publish(_report(run, "restart-job", "c88888", "h-trainer-1.r1"))  # its restart
        for sender in (monitor, stranger):
            sender.bus.publish(_report(run, "monitor-forged", "cmon", trainer))
            sender.bus.publish(job.model_copy(update={"job": "monitor-job", "node": trainer}))

        def forged() -> list[FitnessReport]:
            return [m for m in monitor.of(FitnessReport) if m.fitness == FORGED_FITNESS]

        wait_until(lambda: len(forged()) >= 3, 30, "the forged reports let through")
        assert sorted(m.node for m in forged()) == ["h-trainer-0", "h-trainer-1", "h-trainer-1.r1"]
        on_own_key = next(m for m in forged() if m.node == trainer)
        assert on_own_key.job == job.job  # the one put on h-trainer-1's key, naming the trainer

        # the monitor may ask the coordinator for the births so far
        wait_until(lambda: monitor.of(Birth), 90, "a birth")
        replies = list(monitor.session.get(f"derl/{run}/births/*", timeout=5.0))
        answered = [decode(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
        assert answered and all(isinstance(m, Birth) for m in answered)

        # the run ends, every body born once, over TLS only; no forged report made a birth
        coordinator = processes.started["coordinator"]
        wait_until(lambda: coordinator.poll() is not None, 120, "the run to end")
        assert coordinator.returncode == 0, processes.log("coordinator")
        assert_born_once(run_dir, 3)
        journal = list(replay(run_dir))
        births = [m for m in journal if isinstance(m, Birth)]
        assert {m.node for m in births} == {trainer}
        assert all(m.fitness != FORGED_FITNESS for m in births)
        log = processes.log("coordinator")
        assert f"job {job.job} was never issued to h-trainer-1 for {job.agent}" in log
        assert [m.sender for m in journal if isinstance(m, Rejection)] == [trainer]  # wrong key
        assert "monitor-forged" not in log and "forged-job" not in processes.log("trainer")
        assert max(s.rejected for s in monitor.of(RunStatus)) >= 3

        # what the access control dropped never came, the whole run long
        unseen = ("forged-job", "monitor-job")
        assert not [m for m in monitor.seen if getattr(m, "job", "") in unseen]
        assert stranger.seen == []  # default deny: not even a subscription
        assert len(forged()) == 3

        # the monitor saw the whole run
        kinds = {m.type for m in monitor.seen}
        assert {"TrainJob", "FitnessReport", "Ack", "RunStatus", "Birth"} <= kinds
    finally:
        processes.close()


FORGED_BODY_FITNESS = 55.5  # plausible: within the world's bound, above what the trainer reaches


def test_a_report_with_another_body_than_its_job_is_rejected(tmp_path: Path, procs) -> None:
    """On a run without TLS anyone can publish on a trainer's key (with TLS: a trainer's own
    certificate). A report for a tournament child in flight, published on its trainer's key
    before the trainer's own, naming the trainer and its job, carrying another valid mutated
    body and a plausible fitness: rejected (the coordinator decides every body), and the child
    is born once, from its trainer's report, with its job's body. The trainer is stopped
    (SIGSTOP, well within the transport's lease) from the child's job until the forged report is
    rejected, so its own report comes second on a machine of any speed."""
    local = LocalRun.at(tmp_path, population=2, total=3, train_steps=12288)
    procs.start("coordinator", local.coordinator())
    with observe(local) as observer:
        jobs: queue.Queue[TrainJob] = queue.Queue()
        answers: queue.Queue[Reject] = queue.Queue()
        observer.bus.subscribe(observer.bus.keys.job("a"), jobs.put, (TrainJob,))
        observer.bus.subscribe(observer.bus.keys.ack("a"), answers.put, (Reject,))
        wait_until(lambda: observer.statuses, 60, "the coordinator's status")
        trainer = procs.start("a", local.trainer("a"))
        job = jobs.get(timeout=120)
        forged_body, _ = breed(job.genome, 12345)  # a valid body of an initial body's line
        while job.parent is None:  # the initial bodies' jobs
            job = jobs.get(timeout=120)
        os.killpg(trainer.pid, signal.SIGSTOP)
        try:
            assert forged_body != job.genome
            template = next(m for m in examples(local.run, 0) if isinstance(m, FitnessReport))
            forged = template.model_copy(update={
                "job": job.job, "agent": job.agent, "node": "a", "genome": forged_body,
                "fitness": FORGED_BODY_FITNESS, "env_steps": job.steps})  # fmt: skip
            observer.bus.publish(forged)
            answers.get(timeout=2)
        finally:
            os.killpg(trainer.pid, signal.SIGCONT)
        assert procs.finish(procs.started["coordinator"], timeout=120) == 0
    assert_born_once(local.dir, 3)
    journal = list(replay(local.dir))
    birth = next(m for m in journal if isinstance(m, Birth) and m.agent == job.agent)
    assert birth.fitness != FORGED_BODY_FITNESS and birth.genome != forged_body
    rejects = [m for m in journal if isinstance(m, Reject) and m.job == job.job]
    assert [m.reason for m in rejects] == ["not the body of its job"]
    assert [m.node for m in journal if isinstance(m, TrainJob) and m.agent == job.agent] == ["a"]
