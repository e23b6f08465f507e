"""Crash consistency of a run directory, checked at every point of a real run's writes; prints JSON.

1. Record (`derl.nodes.testing.crash`): a small real run (the smoke profile: P=4, T=2, 10 bodies)
   of a real `derl coordinator` process and two simulated trainers over real Zenoh, under
   `strace -f`: every write of the coordinator and its checkpoint writer, every mark of a trainer
   (a job received, an Ack, a Reject), in the order they completed.
2. Model (`derl.nodes.testing.disk`): the run directory after each operation, as a process kill
   leaves it and as a power cut does under POSIX's rules, journal writes torn inside too.
3. Check (`derl.nodes.testing.crash_check`): each distinct state, started on by a coordinator in
   this process that runs the run to its end with the trainers as they were at the cut: every
   job a trainer received and every acknowledged birth (with its checkpoint) in the journal, no
   child born twice, the run finished with every body born and its results whole. `--real K`
   also checks K states, drawn at random, with a real `derl coordinator` process and the
   trainers over real Zenoh.

Prints: operations recorded, cut points, states tried by kind, distinct states, states checked in
this process and with real processes, failures (each: the cut, the kind of state, what broke),
time. Run: python bench/crash.py [--real K] [--sample N (check N distinct states drawn at random,
not all)] [--work DIR] (about 8 minutes on a shared 2-core machine for every state).
"""

from __future__ import annotations

import argparse
import json
import logging
import random
import shutil
import tempfile
import time
from collections import Counter
from pathlib import Path

from derl.nodes.testing.crash import NODES, PROFILE, record_and_cut
from derl.nodes.testing.crash_check import check_cut


def run(work: Path, sample: int | None, real: int, seed: int = 0) -> dict[str, object]:
    started = time.monotonic()
    recorded = record_and_cut(work)
    rng = random.Random(seed)
    chosen = recorded.distinct
    if sample is not None and sample < len(chosen):
        chosen = rng.sample(chosen, sample)
    failures = list(recorded.refused)
    failures += filter(None, (check_cut(recorded, cut) for cut in chosen))
    reals = rng.sample(chosen, min(real, len(chosen)))
    failures += filter(None, (check_cut(recorded, cut, real=True) for cut in reals))
    return {
        "run": {"profile": PROFILE, "trainers": len(NODES)},
        "operations": dict(Counter(op.kind for op in recorded.ops)),
        "cut_points": len(recorded.ops) + 1,
        "states_tried": dict(recorded.tried),
        "states_tried_total": sum(recorded.tried.values()),
        "distinct_states": len(recorded.distinct),
        "checked_in_process": len(chosen),
        "checked_with_a_real_coordinator": len(reals),
        "failed": len(failures),
        "failures": failures[:20],
        "recorded_and_cut_in_s": round(recorded.seconds, 1),
        "seconds": round(time.monotonic() - started, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sample", type=int, help="check this many distinct states, not all")
    parser.add_argument("--real", type=int, default=3, help="states checked with real processes")
    parser.add_argument("--work", help="folder (default: a temporary one, removed)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="derl-crash-"))
    try:
        print(json.dumps(run(work / "crash", args.sample, args.real), indent=2))
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
