"""What audits cost and how soon they catch a liar: the coordinator's own handlers (`Coordinator`
with `EvolutionRules`, in this process, no bus) driven by simulated trainers in simulated time;
prints JSON, one line per (audit share, seed) and a summary per share.

Each training takes a uniform 0.5-1.5 time units (drawn per job); its result depends only on the
child (training is deterministic), plus 1.0 for the liar (`--liar`: the last trainer). For each
share of audited children: the run's simulated duration, the trainings done, and `throughput`
(births per time unit) and the trainings done over the unaudited run's of the same seed
(`throughput_ratio`, `extra_trainings`: seeds' medians); with a liar, the
births before it was caught and whether any lie stayed. The cost of an audit is its share of
extra trainings, plus the wait of children whose population includes an audited child still in
its second training.
Run: python bench/audit.py [--shares 0 0.02 0.05 0.2] [--trainers 4] [--seeds 3] [--liar]
(`bench/audit_scale.py`: the audit rules at the paper's scale, 288 trainers and 4,000 births.)
"""

from __future__ import annotations

import argparse
import heapq
import json
import random
import statistics
import tempfile
from pathlib import Path

from derl.evolution import EvolutionConfig, load_profile
from derl.messages import Ack, Cancel, Quarantine, Reject, TrainJob, WorkerReady
from derl.nodes.coordinator.node import Coordinator, Liveliness
from derl.nodes.coordinator.run.rules import EvolutionRules
from derl.nodes.testing.trainers import Recorder, honest, honest_report

RUN = "audit"


def simulate(config: EvolutionConfig, trainers: int, seed: int, liar: bool) -> dict[str, object]:
    """One run to its end in simulated time (see the module)."""
    folder = Path(tempfile.mkdtemp(prefix="audit-")) / "run"
    heard = Recorder()
    coordinator = Coordinator(RUN, folder, EvolutionRules(RUN, folder, config), publisher=heard)
    names = [f"t{k}" for k in range(trainers)]
    liar_name = names[-1] if liar else None
    for node in names:
        coordinator.take(Liveliness("trainer", node, True))
    rng = random.Random(seed)
    now, trainings, running = 0.0, 0, []  # running: (finish, node, job)
    holding: dict[str, TrainJob] = {}
    idle = set(names)
    try:
        while not coordinator.state.finished:
            for node in sorted(idle):
                coordinator.take(WorkerReady(run=RUN, node=node, role="trainer", host="s", pid=1))
            coordinator.assign_idle()
            coordinator.settle()
            for msg in heard.messages:
                node = getattr(msg, "node", None)
                if isinstance(msg, TrainJob) and node in idle:
                    idle.discard(node)
                    holding[node] = msg
                    trainings += 1
                    heapq.heappush(running, (now + rng.uniform(0.5, 1.5), node, msg.job))
                elif (
                    isinstance(msg, Ack | Reject | Cancel) and holding.get(node, msg).job == msg.job
                ):
                    holding.pop(node)
                    idle.add(node)
                    running = [r for r in running if r[2] != msg.job]
                    heapq.heapify(running)
            heard.messages.clear()
            if not running:
                if coordinator.state.finished:
                    break
                raise RuntimeError(f"stalled at {coordinator.rules.born} born")
            now, node, _ = heapq.heappop(running)
            coordinator.take(honest_report(holding[node], 1.0 if node == liar_name else 0.0))
            coordinator.settle()
        state = coordinator.state
        quarantine = next(iter(state.quarantined.values()), None)
        return {
            "duration": round(now, 3),
            "trainings": trainings,
            "born": len(state.births),
            "audited": len(state.checked),
            "caught_after_births": _births_before(folder, quarantine) if quarantine else None,
            "lies_left": sum(b.fitness != honest(b.genome) for b in state.births),
            "caught": quarantine is not None,
        }
    finally:
        coordinator.close()


def _births_before(folder: Path, quarantine: Quarantine) -> int:
    from derl.messages import Birth
    from derl.nodes.journal.segments import replay

    births = 0
    for msg in replay(folder):
        if msg == quarantine:
            return births
        births += isinstance(msg, Birth)
    return births


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shares", type=float, nargs="+", default=[0.0, 0.02, 0.05, 0.2])
    parser.add_argument("--trainers", type=int, default=4)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--profile", default="demo")
    parser.add_argument("--liar", action="store_true", help="the last trainer adds 1.0")
    args = parser.parse_args()
    base = load_profile(args.profile).model_copy(update={"eval_top": 0, "eval_tasks": ()})
    results: dict[float, list[dict[str, object]]] = {}
    for share in args.shares:
        for seed in range(args.seeds):
            config = base.model_copy(update={"audit": share, "seed": seed})
            result = {
                "share": share,
                "seed": seed,
                **simulate(config, args.trainers, seed, args.liar),
            }
            results.setdefault(share, []).append(result)
            print(json.dumps(result), flush=True)
    unaudited = results.get(0.0)
    for share, runs in results.items():
        summary: dict[str, object] = {"summary": share, "profile": args.profile,
                                       "trainers": args.trainers}  # fmt: skip
        if unaudited is not None:
            pairs = list(zip(runs, unaudited, strict=True))
            more = statistics.median(r["trainings"] / b["trainings"] - 1 for r, b in pairs)
            ratio = statistics.median(b["duration"] / r["duration"] for r, b in pairs)
            summary |= {"extra_trainings": round(more, 4), "throughput_ratio": round(ratio, 4)}
        if args.liar:
            caught = [r["caught_after_births"] for r in runs if r["caught"]]
            summary["caught"] = f"{len(caught)}/{len(runs)}"
            summary["caught_after_births_median"] = statistics.median(caught) if caught else None
            summary["lies_left"] = sum(r["lies_left"] for r in runs)
        print(json.dumps(summary), flush=True)


if __name__ == "__main__":
    main()
