"""What a flood from one trainer identity costs a coordinator: its journal's growth and its memory;
prints JSON.

A real `derl coordinator` process (the smoke profile, a run that never ends) on loopback, and one
flooder over one Zenoh session: a trainer `evil` (its liveliness token up) that asks for a job,
reports it (an untrained policy of the job's body: a valid report, born), then, for `--seconds`,
sends as fast as its session allows, in turn (`--kinds`: some of them): a copy of that report (a
duplicate of a born child's: answered, not journaled), a report for a job never given to it,
under its name or a restart name `evil.r<n>` (refused: a share of them journaled a minute,
`JOURNALED_REFUSALS`), and its WorkerReady. Every `--every` seconds: the journal's bytes and
the coordinator's resident memory. `growth_per_min_kb` is the journal's growth over the flood's
second half, per minute.
Run: python bench/flood.py [--seconds 600] [--every 30]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path

import yaml

from derl.messages import Ack, FitnessReport, Reject, TrainJob, WorkerReady
from derl.nodes.coordinator.ledger import JOURNALED_REFUSALS
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.runtime.ports import free_port
from derl.nodes.runtime.processes import spawn_derl, stop_all
from derl.nodes.testing.trainers import untrained_policy

RUN = "flood"
PROFILE = {"profile": "smoke", "total": 1000, "eval_top": 0, "eval_tasks": [], "lease_s": 3600.0}


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _journal_bytes(run_dir: Path) -> int:
    return sum(p.stat().st_size for p in (run_dir / "journal").glob("*.mcap"))


def report_for(job: TrainJob) -> FitnessReport:
    from derl.messages import Curve

    return FitnessReport(
        run=RUN, agent=job.agent, job=job.job, node=job.node, genome=job.genome, fitness=1.0,
        fitness_source="window", fitness_episodes=1, curve=Curve(env_steps=(1,), returns=(0.0,)),
        energy=1.0, cost_of_work=1.0, mass=1.0, episodes=1, env_steps=job.steps, wall_s=0.0,
        steps_per_s=0.0, checkpoint=untrained_policy(job.genome, job.task),
    )  # fmt: skip


KINDS = ("duplicate", "never_issued", "ready")


def flood(seconds: float, every: float, work: Path, kinds: tuple[str, ...] = KINDS
          ) -> dict[str, object]:  # fmt: skip
    profile, run_dir = work / "flood.yaml", work / "run"
    profile.write_text(yaml.safe_dump(PROFILE))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    coordinator = spawn_derl(
        ["coordinator", "--run", RUN, "--profile", str(profile), "--run-dir", str(run_dir),
         "--listen", endpoint], work / "coordinator.log",
    )  # fmt: skip
    jobs: list[TrainJob] = []
    answers = {"Ack": 0, "Reject": 0}
    samples, sent = [], dict.fromkeys(kinds, 0)
    try:
        with open_session(ZenohOptions(connect=(endpoint,))) as session:
            bus = Bus(session, RUN)
            token = bus.token("trainer", "evil")
            bus.subscribe(bus.keys.job("evil"), jobs.append, (TrainJob,))
            for name in ("evil", "evil.r1", "evil.r2"):
                bus.subscribe(bus.keys.ack(name),
                              lambda m: answers.__setitem__(m.type, answers[m.type] + 1),
                              (Ack, Reject))  # fmt: skip
            ready = WorkerReady(run=RUN, node="evil", role="trainer", host="h", pid=1)
            deadline = time.monotonic() + 120
            while not jobs:
                if time.monotonic() > deadline:
                    raise TimeoutError("no job came")
                bus.publish(ready)
                time.sleep(0.5)
            report = report_for(jobs[0])
            while answers["Ack"] == 0:
                bus.publish(report)
                time.sleep(0.5)
            time.sleep(2)
            stop = threading.Event()
            start = time.monotonic()

            def sample() -> None:
                rss = round(_rss_mb(coordinator.pid), 1)
                samples.append({"t": round(time.monotonic() - start, 1),
                                "journal_bytes": _journal_bytes(run_dir),
                                "coordinator_rss_mb": rss})  # fmt: skip

            def sampler() -> None:
                while not stop.wait(every):
                    sample()

            sample()
            thread = threading.Thread(target=sampler, daemon=True)
            thread.start()
            k = 0
            while time.monotonic() - start < seconds:
                name = ("evil", "evil.r1", "evil.r2")[k % 3]
                forged = report.model_copy(update={"node": name, "job": f"forged.{k}"})
                for kind, msg in zip(KINDS, (report, forged, ready), strict=True):
                    if kind in sent:
                        bus.publish(msg)
                        sent[kind] += 1
                k += 1
            stop.set()
            thread.join()
            token.undeclare()
    finally:
        stop_all([coordinator])
    half = [s for s in samples if s["t"] >= seconds / 2]
    growth = (half[-1]["journal_bytes"] - half[0]["journal_bytes"]) / max(
        (half[-1]["t"] - half[0]["t"]) / 60, 1e-9
    )
    return {
        "seconds": seconds,
        "sent": sent,
        "sent_per_s": round(sum(sent.values()) / seconds),
        "answers_heard": answers,
        "journaled_refusals_per_min_allowed": JOURNALED_REFUSALS,
        "journal_growth_bytes": samples[-1]["journal_bytes"] - samples[0]["journal_bytes"],
        "growth_per_min_kb": round(growth / 1024, 1),
        "coordinator_rss_mb": [samples[0]["coordinator_rss_mb"], samples[-1]["coordinator_rss_mb"]],
        "samples": samples,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=600.0)
    parser.add_argument("--every", type=float, default=30.0)
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="flood-") as work:
        result = flood(args.seconds, args.every, Path(work), tuple(args.kinds))
        print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
