"""A run on a shared network: mutual TLS with certificates made by openssl here, and Zenoh access
control keyed on the certificates' common names, from the shipped config templates
(launch/zenoh/tls-node.json5, tls-monitor.json5) that every node takes with --zenoh-config.

Shown with real node processes on loopback (multicast off):
- a coordinator and a trainer holding valid certificates run a tiny run to its end;
- a client with no certificate, with a certificate from another CA, or speaking plain TCP cannot
  connect; a certificate from the right CA with an unknown name connects but sees nothing and
  delivers nothing (default deny);
- a monitor identity (CN derl-monitor) sees the whole run, but its jobs and fitness reports reach
  nobody, while the same kind of report from a node identity is delivered;
- a fitness report for a never-issued job, one for a real job from a node that does not hold
  it, and one from the node that holds it but with another body than its job's, are rejected by
  the coordinator: not acknowledged, counted in RunStatus.rejected.
"""

from __future__ import annotations

import json
import queue
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from nodes_fixtures import (
    REPO,
    Processes,
    assert_born_once,
    derl_argv,
    free_port,
    run_id,
    wait_for,
    write_profile,
)

from messages import Ack, Birth, FitnessReport, MessageBase, RunStatus, TrainJob, decode
from messages.examples import examples
from nodes.journal.segments import replay
from nodes.runtime.bus import Bus, ZenohOptions, zenoh_config

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl")

TEMPLATES = REPO / "launch" / "zenoh"
IDENTITIES = ("derl-coordinator", "derl-trainer", "derl-monitor", "derl-stranger")


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def _ca(folder: Path, name: str) -> None:
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
             "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.pem", "-days", "2",
             "-subj", f"/CN={name}", cwd=folder)  # fmt: skip


def _certificate(folder: Path, ca: str, name: str, file: str) -> None:
    (folder / f"{file}.ext").write_text(
        "subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n"
    )
    _openssl(
        "req",
        "-newkey",
        "ec",
        "-pkeyopt",
        "ec_paramgen_curve:prime256v1",
        "-nodes",
        "-keyout",
        f"{file}.key",
        "-out",
        f"{file}.csr",
        "-subj",
        f"/CN={name}",
        cwd=folder,
    )
    _openssl("x509", "-req", "-in", f"{file}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
             "-CAcreateserial", "-out", f"{file}.pem", "-days", "2", "-extfile", f"{file}.ext",
             cwd=folder)  # fmt: skip


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The run's CA with one certificate per identity, and an impostor: CN derl-trainer from
    another CA."""
    folder = tmp_path_factory.mktemp("pki")
    _ca(folder, "ca")
    for identity in IDENTITIES:
        _certificate(folder, "ca", identity, identity)
    _ca(folder, "other-ca")
    _certificate(folder, "other-ca", "derl-trainer", "impostor")
    return folder


def _node_config(pki: Path, identity: str, folder: Path) -> Path:
    """tls-node.json5 with this identity's certificate (the template's paths replaced)."""
    text = (TEMPLATES / "tls-node.json5").read_text()
    for template, real in (("certs/ca.pem", pki / "ca.pem"),
                           ("certs/node.pem", pki / f"{identity}.pem"),
                           ("certs/node.key", pki / f"{identity}.key")):  # fmt: skip
        assert f'"{template}"' in text
        text = text.replace(f'"{template}"', json.dumps(str(real)))
    path = folder / f"{identity}.json5"
    path.write_text(text)
    return path


def _client_config(pki: Path, cert: str | None, folder: Path, ca: str = "ca") -> Path:
    """tls-monitor.json5 (a client) with the given certificate, or none at all."""
    text = (TEMPLATES / "tls-monitor.json5").read_text()
    text = text.replace('"certs/ca.pem"', json.dumps(str(pki / f"{ca}.pem")))
    if cert is None:
        text = text.replace('connect_certificate: "certs/monitor.pem",', "")
        text = text.replace('connect_private_key: "certs/monitor.key",', "")
    else:
        text = text.replace('"certs/monitor.pem"', json.dumps(str(pki / f"{cert}.pem")))
        text = text.replace('"certs/monitor.key"', json.dumps(str(pki / f"{cert}.key")))
    path = folder / f"client-{cert}.json5"
    path.write_text(text)
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


FORGED_FITNESS = -4242.0


def _report(run: str, job: str, child: str, node: str) -> FitnessReport:
    template = next(m for m in examples(run, 0) if isinstance(m, FitnessReport))
    update = {"job": job, "child": child, "node": node, "fitness": FORGED_FITNESS}
    return template.model_copy(update=update)


def test_tls_and_access_control(tmp_path: Path, pki: Path, sessions: list) -> None:
    run, run_dir = run_id(), tmp_path / "run"
    profile = write_profile(tmp_path / "profile.yaml", total=3, train_steps=16384)
    port, trainer_port = free_port(), free_port()
    seed = f"tls/127.0.0.1:{port}"
    configs = {identity: _node_config(pki, identity, tmp_path) for identity in IDENTITIES}
    processes = Processes(tmp_path / "logs")
    try:
        processes.start("coordinator", derl_argv(
            "coordinator", "--run", run, "--profile", str(profile), "--run-dir", str(run_dir),
            "--listen", seed, "--zenoh-config", str(configs["derl-coordinator"])))  # fmt: skip
        wait_for(lambda: "replayed" in processes.log("coordinator"), 60, "the coordinator")

        # (b) no way in without a certificate from the run's CA, or without TLS
        def client(config: Path | None, endpoint: str = seed) -> ZenohOptions:
            return ZenohOptions(mode="client", connect=(endpoint,), config_file=config)

        refused = {
            "no certificate": client(_client_config(pki, None, tmp_path)),
            "another CA": client(_client_config(pki, "impostor", tmp_path)),
            "plain tcp": client(None, f"tcp/127.0.0.1:{port}"),
        }
        for why, options in refused.items():
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                _open(options).close()
                pytest.fail(f"a client with {why} connected")

        def tap(config: Path, mode: str = "client", endpoint: str = seed) -> Tap:
            options = ZenohOptions(mode=mode, connect=(endpoint,), config_file=config)
            sessions.append(_open(options))
            return Tap(sessions[-1], run)

        witness = tap(_client_config(pki, "derl-trainer", tmp_path))  # a node identity
        monitor = tap(_client_config(pki, "derl-monitor", tmp_path))
        stranger = tap(_client_config(pki, "derl-stranger", tmp_path))  # right CA, unknown CN
        control = tap(_client_config(pki, "derl-trainer", tmp_path))  # controls: node identities
        boss = tap(_client_config(pki, "derl-coordinator", tmp_path))
        acks = control.bus.inbox(control.bus.keys.ack("impostor"), (Ack,))
        processes.start("trainer", derl_argv(  # once every tap listens
            "trainer", "--run", run, "--name", "trainer-0", "--connect", seed,
            "--listen", f"tls/127.0.0.1:{trainer_port}",
            "--zenoh-config", str(configs["derl-trainer"])))  # fmt: skip

        # a real job in flight: a report for it from a node that does not hold it
        job = witness.jobs.get(timeout=90)
        control.bus.publish(_report(run, job.job, job.child, "impostor"))
        control.bus.publish(_report(run, "never-issued", "c77777", "trainer-0"))
        # from the node that holds the job, but with a body that is not its job's
        wrong_body = _report(run, job.job, job.child, "trainer-0")
        assert wrong_body.genome != job.genome
        control.bus.publish(wrong_body.model_copy(update={"mutation": None}))
        nobody = job.model_copy(update={"job": "control-job", "child": "cnobody", "node": "nobody"})
        boss.bus.publish(nobody)  # to a trainer that does not exist: harmless, but delivered
        # a monitor that goes straight to the trainer, as a peer: the trainer's ACL stops it
        direct = tap(_client_config(pki, "derl-monitor", tmp_path), "peer",
                     f"tls/127.0.0.1:{trainer_port}")  # fmt: skip
        wait_for(lambda: list(direct.session.info.peers_zid()), 10, "the monitor peer linked")
        for _ in range(5):
            for sender in (monitor, stranger, direct):
                for node in ("trainer-0", "nobody"):
                    forged = {"job": "monitor-job", "child": "cmon", "node": node}
                    sender.bus.publish(job.model_copy(update=forged))
                sender.bus.publish(_report(run, "monitor-forged", "cmon", "trainer-0"))
                sender.bus.publish(_report(run, job.job, job.child, "trainer-0"))
            time.sleep(0.4)
        time.sleep(1)

        # (c) nobody saw what the monitor (or the stranger) published; what node identities
        # published was delivered
        assert [m.job for m in witness.of(TrainJob) if m.node == "nobody"] == ["control-job"]
        assert not [m for m in witness.seen if getattr(m, "job", "") == "monitor-job"]
        forged = [m for m in witness.of(FitnessReport) if m.fitness == FORGED_FITNESS]
        assert {m.node for m in forged} == {"impostor", "trainer-0"}  # the control's reports
        assert len(forged) == 3 and not [m for m in forged if m.job == "monitor-forged"]

        # (a) the run ends, every body born once, over TLS only
        coordinator = processes.started["coordinator"]
        wait_for(lambda: coordinator.poll() is not None, 120, "the run to end")
        assert coordinator.returncode == 0, processes.log("coordinator")
        assert_born_once(run_dir, 3)
        born = {m.child: m.node for m in replay(run_dir) if isinstance(m, Birth)}
        assert born[job.child] == "trainer-0"
        births = [m for m in replay(run_dir) if isinstance(m, Birth)]
        assert all(m.fitness != FORGED_FITNESS for m in births)  # no forged report made a birth

        # rejections: not acknowledged, counted (and the forgeries never reached anyone)
        assert acks.empty()
        log = processes.log("coordinator")
        assert f"job {job.job} was never issued to impostor" in log
        assert "job never-issued was never issued to trainer-0" in log
        assert f"rejected fitness of {job.child} from trainer-0" in log
        assert max(s.rejected for s in monitor.of(RunStatus)) == 3
        assert "monitor-forged" not in log and "monitor-job" not in processes.log("trainer")

        # (c) the monitor saw the whole run; the stranger saw nothing
        kinds = {m.type for m in monitor.seen if m.run == run}
        assert {"TrainJob", "FitnessReport", "Ack", "RunStatus", "Tournament"} <= kinds
        assert stranger.seen == []  # default deny: not even a subscription
    finally:
        processes.close()
