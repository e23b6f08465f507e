"""A run across real hosts: three network namespaces (coordinator, hostA, hostB), each with its
own loopback and a veth link to a bridge in a fourth namespace, all made (and deleted) by the
test. Each host runs `derl launch LAUNCH --host NAME` from one launch file: a peer mesh over TCP
seeded by the coordinator's endpoint. Once a hostA trainer holds a job, hostA freezes, drops off
the network (its link goes down) and its processes are SIGKILLed: the run carries on on hostB, and
every body is born exactly once.

Needs root and `ip netns` (iproute2); skipped with the reason otherwise.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml
from nodes_fixtures import (
    Processes,
    assert_born_once,
    in_training,
    jobs,
    journaled,
    run_id,
    write_profile,
)

from derl.messages import Birth
from derl.nodes.testing.waiting import wait_until

SUBNET = "10.213.0"  # only ever inside the namespaces this test makes
HOSTS = {"coord": 1, "hostA": 2, "hostB": 3}  # host name -> last octet of its address
PORT = 7447


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check, timeout=20)


def _why_not() -> str | None:
    if sys.platform != "linux":
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "needs root to create network namespaces and veth links"
    if shutil.which("ip") is None:
        return "needs the `ip` command (iproute2)"
    probe = f"derlprobe{uuid.uuid4().hex[:6]}"
    made = _ip("netns", "add", probe, check=False)
    if made.returncode != 0:
        return f"`ip netns add` failed: {made.stderr.strip()}"
    _ip("netns", "del", probe, check=False)
    return None


class Network:
    """The namespaces and links of one test; `close` kills everything in them and deletes them."""

    def __init__(self) -> None:
        tag = uuid.uuid4().hex[:6]
        self.bridge = f"derl{tag}br"
        self.ns = {host: f"derl{tag}{host}" for host in HOSTS}
        self.made: list[str] = []
        try:
            self._add(self.bridge)
            _ip("-n", self.bridge, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.bridge, "link", "set", "br0", "up")
            for k, (host, octet) in enumerate(HOSTS.items()):
                ns, port = self.ns[host], f"p{k}"
                self._add(ns)
                _ip("link", "add", "eth0", "netns", ns, "type", "veth",
                    "peer", "name", port, "netns", self.bridge)  # fmt: skip
                _ip("-n", self.bridge, "link", "set", port, "master", "br0")
                _ip("-n", self.bridge, "link", "set", port, "up")
                _ip("-n", ns, "addr", "add", f"{SUBNET}.{octet}/24", "dev", "eth0")
                _ip("-n", ns, "link", "set", "eth0", "up")
                _ip("-n", ns, "link", "set", "lo", "up")
        except BaseException:
            self.close()
            raise

    def _add(self, name: str) -> None:
        _ip("netns", "add", name)
        self.made.append(name)

    def address(self, host: str) -> str:
        return f"{SUBNET}.{HOSTS[host]}"

    def exec(self, host: str, *argv: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns[host], *argv]

    def pids(self, host: str) -> list[int]:
        found = _ip("netns", "pids", self.ns[host], check=False)
        return [int(pid) for pid in found.stdout.split()]

    def kill_all(self, host: str, sig: int = signal.SIGKILL) -> None:
        for pid in self.pids(host):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)

    def link_down(self, host: str) -> None:
        _ip("-n", self.ns[host], "link", "set", "eth0", "down")

    def established(self, host: str) -> set[tuple[str, int]]:
        """Remote (address, port) of the established TCP connections inside `host`."""
        table = subprocess.run(self.exec(host, "cat", "/proc/net/tcp"), capture_output=True,
                               text=True, check=True, timeout=20).stdout  # fmt: skip
        remotes = set()
        for line in table.splitlines()[1:]:
            fields = line.split()
            if fields[3] != "01":  # TCP_ESTABLISHED
                continue
            address, port = fields[2].split(":")
            ip = socket.inet_ntoa(int(address, 16).to_bytes(4, "little"))
            remotes.add((ip, int(port, 16)))
        return remotes

    def close(self) -> None:
        for ns in reversed(self.made):
            for pid in _ip("netns", "pids", ns, check=False).stdout.split():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(int(pid), signal.SIGKILL)
            _ip("netns", "del", ns, check=False)
        self.made.clear()


@pytest.fixture
def network() -> Iterator[Network]:
    reason = _why_not()
    if reason:
        pytest.skip(reason)
    net = Network()
    try:
        yield net
    finally:
        net.close()
        left = _ip("netns", "list", check=False).stdout
        assert not any(ns in left for ns in [net.bridge, *net.ns.values()]), left


def _launch_file(tmp: Path, net: Network) -> Path:
    def host(name: str, nodes: list[dict]) -> dict:
        address = net.address(name)
        return {"name": name, "address": address, "listen": f"tcp/{address}:{PORT}",
                "nodes": nodes}  # fmt: skip

    launch = {
        "run": run_id(),
        "run_dir": str(tmp / "run"),
        # ~1-2 s trainings: the test sees a hostA trainer's job and freezes hostA within them
        "profile": str(write_profile(tmp / "profile.yaml", total=4, train_steps=24576)),
        "topology": {"kind": "peer_mesh", "seed": f"tcp/{net.address('coord')}:{PORT}"},
        "hosts": [
            host("coord", [{"role": "coordinator", "restart": "on-failure"}]),
            host("hostA", [{"role": "trainer", "count": 2, "restart": "on-failure"}]),
            host("hostB", [{"role": "trainer", "count": 1, "restart": "on-failure"}]),
        ],
    }
    path = tmp / "cluster.yaml"
    path.write_text(yaml.safe_dump(launch, sort_keys=False))
    return path


@pytest.mark.slow
def test_run_survives_a_host_dropping_off(tmp_path: Path, network: Network) -> None:
    launch = _launch_file(tmp_path, network)
    run_dir = tmp_path / "run"
    processes = Processes(tmp_path / "test-logs")
    try:
        for host in HOSTS:
            argv = [sys.executable, "-m", "derl.nodes.cli", "launch", str(launch), "--host", host]
            processes.start(host, network.exec(host, *argv))
        # the mesh: hostB's trainer talks to hostA's trainers directly (gossip), not only to
        # the seed, over the namespaces' own addresses
        wait_until(
            lambda: {ip for ip, _ in network.established("hostB")} >= {
                network.address("coord"), network.address("hostA")},
            60, "hostB connected to coord and hostA",
        )  # fmt: skip

        wait_until(lambda: [j for j in in_training(run_dir) if j.node.startswith("hostA-")],
                   120, "a job held by a hostA trainer")  # fmt: skip
        network.kill_all("hostA", signal.SIGSTOP)  # frozen at once: its job stays unreported
        network.link_down("hostA")  # hostA vanishes: no FIN, the lease (2.5 s) notices
        network.kill_all("hostA")
        wait_until(lambda: processes.started["coord"].poll() is not None, 180, "the run to end")
        assert processes.started["coord"].returncode == 0, processes.log("coord")
        assert_born_once(run_dir, 4)
        on_a = {b.agent for b in journaled(run_dir, Birth) if b.node.startswith("hostA-")}
        held = {j.agent for j in jobs(run_dir) if j.node.startswith("hostA-")} - on_a
        assert held, "hostA's trainers finished their jobs before the test cut them off"
        after = [j for j in jobs(run_dir) if j.agent in held and j.node.startswith("hostB-")]
        assert {j.agent for j in after} == held  # hostA's bodies were trained on hostB
        coordinator_log = (run_dir / "logs" / "coord-coordinator-0.log").read_text()
        assert "hostA-trainer-" in coordinator_log and "goes back to the queue" in coordinator_log
        wait_until(lambda: processes.started["hostB"].poll() is not None, 30, "hostB's launcher")
        assert processes.started["hostB"].returncode == 0, processes.log("hostB")
    finally:
        processes.close()
        for host in HOSTS:
            network.kill_all(host)


def test_without_root_or_ip_the_test_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    assert _why_not() == "needs root to create network namespaces and veth links"
    monkeypatch.setattr(os, "geteuid", lambda: 0)
    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert _why_not() == "needs the `ip` command (iproute2)"
