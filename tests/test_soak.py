"""The soak (`derl.nodes.testing.soak`; bench/soak.py runs it for half an hour) in short: a run
of under a minute under `derl launch` in router topology, a fault drawn at random every 2 to 4 s
(SIGKILL or SIGSTOP of a trainer, the evaluator, the coordinator or the router; garbage on the
bus), every node's memory, open files and threads sampled. It finishes, every child is born once,
each node was sampled, and the processes that lived long enough (the launch at least) were
judged. Whether the figures stay flat is the 30-minute soak's question (a minute is mostly
warm-up): this test checks that they are measured and reported."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest

from derl.nodes.testing.soak import Soak

pytestmark = pytest.mark.slow


def test_a_short_soak_finishes_with_every_child_born_once(tmp_path: Path) -> None:
    # faults every 2-4 s, for 24 s at most (twice `minutes`), over 24 bodies. Seed 82 draws first
    # a stop of the router for 24 s (at 5 s, before a quick machine could have finished the run),
    # then six faults of four more kinds while it is stopped: a run of any speed lasts past them
    # all, and long enough (over 30 s) for the launch to be judged. A soak of seed 1 finished in
    # under 10 s on a fast machine, before its third fault, and judged nothing.
    soak = Soak(tmp_path, minutes=0.2, fault_every=(2.0, 4.0), total=24, trainers=2, seed=82,
                train_steps=4096)  # fmt: skip
    report = soak.execute()
    print(json.dumps({k: v for k, v in report.items() if k != "fault_log"}, indent=1))
    assert report["finished"], report["fault_log"]
    assert report["born_once"] and report["born"] + report["given_up"] == 24, report
    assert report["faults"] >= 3 and len(report["faults_by_kind"]) >= 2, report["fault_log"]
    roles = Counter()
    for name, count in report["incarnations"].items():
        roles[name.split()[0]] += count
    assert {"launch", "router", "coordinator", "checkpoint_writer", "evaluator"} <= set(roles)
    assert roles["trainer"] >= 2, roles
    judged = report["judged_processes"]
    # the launch, which no fault strikes, is sampled from start to end: it is judged at least
    assert "launch" in judged, judged
    for incarnations in judged.values():
        for figures in incarnations:
            assert {"rss_mb", "open_files", "threads", "flat"} <= set(figures)
