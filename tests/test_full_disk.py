"""A full disk under a running coordinator (a real `derl coordinator` and trainers over real Zenoh,
the writes failing in the kernel: a small tmpfs filled up, or the writers' file-size limit): it
acknowledges nothing while its journal cannot be written, says which file failed and why (once,
not once per retry), keeps its state and its process, and carries on by itself when the disk has
room again; every birth it had acknowledged is kept, none is born twice, the run finishes."""

from __future__ import annotations

import time
from pathlib import Path

from nodes_fixtures import (
    FullDisk,
    LocalRun,
    Processes,
    assert_born_once,
    journaled,
    observe,
    wait_for,
)

from derl.messages import Ack, Birth

FAULT_S = 4.0  # how long the disk stays full once the coordinator has said so


def test_a_full_disk_stalls_the_coordinator_until_it_has_room(
    tmp_path: Path, procs: Processes, full_disk: FullDisk
) -> None:
    local = LocalRun(full_disk.path / "run", tmp_path / "profile.yaml")
    LocalRun.at(tmp_path, population=2, total=8, train_steps=8192)  # writes the profile
    coordinator = procs.start("coordinator", local.coordinator())
    with observe(local) as observer:
        heard: list[Birth | Ack] = []
        observer.bus.subscribe(observer.bus.keys.all("births"), heard.append, (Birth,))
        observer.bus.subscribe(observer.bus.keys.all("ack"), heard.append, (Ack,))
        wait_for(lambda: observer.statuses, 60, "the coordinator's status")
        for name in ("a", "b"):
            procs.start(name, local.trainer(name))
        wait_for(lambda: sum(isinstance(m, Birth) for m in heard) >= 2, 120, "two births")
        full_disk.fill([coordinator.pid])
        try:
            said = wait_for(lambda: "cannot write" in procs.log("coordinator"), 60, "a failure")
            assert said
            time.sleep(1.0)  # what was on the disk before may still go out
            before = len(heard)
            time.sleep(FAULT_S)
            assert len(heard) == before, "acknowledged or born while nothing could be written"
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
    for name in ("a", "b"):
        assert procs.finish(procs.started[name], timeout=30) == 0
