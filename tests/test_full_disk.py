"""A full disk under a running coordinator (a real `derl coordinator` and trainers over real Zenoh,
the writes failing in the kernel: a small tmpfs filled up, or the writers' file-size limit): it
acknowledges nothing while its journal cannot be written, says which file failed and why (once,
not once per retry), keeps its state and its process, and carries on by itself when the disk has
room again; every birth it had acknowledged is kept, none is born twice, the run finishes. A
monitor that reads each born agent's checkpoint file the moment it hears the Birth finds it
whole, full disk or not."""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

from nodes_fixtures import (
    FullDisk,
    LocalRun,
    Processes,
    assert_born_once,
    journaled,
    observe,
)

from derl.messages import Ack, Birth, FitnessReport
from derl.nodes.testing.waiting import wait_until

FAULT_S = 4.0  # how long the disk stays full once the coordinator has said so


def test_a_full_disk_stalls_the_coordinator_until_it_has_room(
    tmp_path: Path, procs: Processes, full_disk: FullDisk
) -> None:
    local = LocalRun(full_disk.path / "run", tmp_path / "profile.yaml")
    LocalRun.at(tmp_path, population=2, total=8, train_steps=8192)  # writes the profile
    coordinator = procs.start("coordinator", local.coordinator())
    with observe(local) as observer:
        heard: list[Birth | Ack] = []
        loaded: dict[str, bytes | None] = {}  # agent -> its file's SHA-256 when its Birth came

        def load(birth: Birth) -> None:
            file = local.dir / "checkpoints" / f"{birth.agent}.pt"
            loaded[birth.agent] = (
                hashlib.sha256(file.read_bytes()).digest() if file.exists() else None
            )
            heard.append(birth)

        observer.bus.subscribe(observer.bus.keys.all("births"), load, (Birth,))
        observer.bus.subscribe(observer.bus.keys.all("ack"), heard.append, (Ack,))
        wait_until(lambda: observer.statuses, 60, "the coordinator's status")
        for name in ("a", "b"):
            procs.start(name, local.trainer(name))
        wait_until(lambda: sum(isinstance(m, Birth) for m in heard) >= 2, 120, "two births")
        full_disk.fill([coordinator.pid])
        try:
            wait_until(lambda: "cannot write" in procs.log("coordinator"), 60, "a failure")
            time.sleep(FAULT_S)  # the disk stays full a while: the coordinator tries again
            said = {m.agent for m in list(heard)}  # then what is on the disk (it cannot grow)
            on_disk = {m.agent for m in journaled(local.dir, Birth)}
            assert said <= on_disk, "acknowledged or born what is not on the disk"
            assert coordinator.poll() is None
        finally:
            full_disk.free()
        assert procs.finish(coordinator, timeout=180) == 0, procs.log("coordinator")
    log = procs.log("coordinator")
    failures = [line for line in log.splitlines() if "cannot write" in line]
    assert len(failures) == 1, failures  # said once, not once per retry
    reason = "No space left on device" if full_disk.kind == "tmpfs" else "File too large"
    assert str(local.dir) in failures[0] and reason in failures[0]
    assert "writing works again" in log
    assert_born_once(local.dir, 8)
    births = {m.agent: m for m in journaled(local.dir, Birth)}
    for msg in heard:  # every birth and Ack published is in the journal
        assert msg.agent in births and (isinstance(msg, Birth) or births[msg.agent].job == msg.job)
    sha256 = {r.job: r.checkpoint for r in journaled(local.dir, FitnessReport)}
    for agent, digest in loaded.items():  # each born agent's checkpoint, read on its Birth
        assert digest == sha256[births[agent].job], f"{agent} was born before its checkpoint"
    for name in ("a", "b"):
        assert procs.finish(procs.started[name], timeout=30) == 0
