"""A long run under random faults, every node's resources sampled; prints JSON.

The soak itself (a run under `derl launch` in router topology, a fault drawn at random every 20
to 60 s: SIGKILL or SIGSTOP of a node, garbage on the bus; every node process sampled; the
report: `finished`, `born_once`, `flat`) is `derl.nodes.testing.soak` (nodes/testing/soak.py),
which tests/test_soak.py runs for a minute. This script chooses the number of bodies so that the
run lasts about `--minutes` on this machine (a calibration training first, unless `--total` is
given), runs it and prints its report.
Run: python bench/soak.py [--minutes 30] [--fault-every 20 60] [--seed 0] [--trainers 2]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

from derl.nodes.testing.soak import PROFILE, Soak


def calibrate(train_steps: int) -> float:
    """Seconds one training of the soak's profile takes here (a sampled body, in FT; the second
    of two: the first pays for the imports and the first compiles)."""
    import numpy as np

    from derl.lifetime import learn
    from derl.rl import PPOConfig
    from derl.unimal import sample_population

    config = PPOConfig(total_steps=train_steps, num_envs=PROFILE["num_envs"])
    first, second = sample_population(2, np.random.default_rng(0))
    learn(first, "ft", config)
    start = time.monotonic()
    learn(second, "ft", config)
    return time.monotonic() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--fault-every", type=float, nargs=2, default=(20.0, 60.0))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trainers", type=int, default=2)
    parser.add_argument("--train-steps", type=int, default=PROFILE["train_steps"])
    parser.add_argument("--total", type=int, help="bodies (default: about --minutes of them)")
    parser.add_argument("--work", help="folder for the run (default: a temp folder)")
    parser.add_argument("--keep", action="store_true", help="keep the run's folder")
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    total = args.total
    if total is None:  # the trainers in parallel, with a margin (a soak longer than asked is
        # fine, a shorter one is not; a body born already is born at once, untrained)
        body_s = calibrate(args.train_steps)
        bodies = args.minutes * 60 / body_s * args.trainers * 1.3
        total = max(PROFILE["population"] + 2, int(bodies))
    work = Path(tempfile.mkdtemp(prefix="derl-soak-", dir=args.work))
    soak = Soak(work, args.minutes, tuple(args.fault_every), total, args.trainers, args.seed,
                args.train_steps)  # fmt: skip
    try:
        out = soak.execute()
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    out["work"] = str(work)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
