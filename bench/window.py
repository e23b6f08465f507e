"""What keeping a run a function of its seed costs: trainer throughput with the evolution's
window (`in_flight` W = 2x and 4x the trainers) against free-running (W = 0); prints JSON.

Child n is bred from the population of the first n - W children, so a trainer whose next child's
population is not known yet (a child before it still training) waits. Two measurements:
- ``simulated`` (default): the coordinator's own state machine (`bench/repeats.py`'s `simulate`:
  `derl.evolution.Evolution`, its repeats and holds) with trainings of a uniform 0.5-1.5 time
  units, for a profile at many trainer counts; `utilisation` is the trainers' busy time over
  trainers x the run's duration, `ratio` a window's utilisation over free-running's, each the
  median over seeds of runs that differ only in the window.
- ``--real``: real `derl coordinator` and `derl trainer` processes on loopback, a small profile
  (P 16, 48 bodies of 16,384 FT steps) run free-running and with each window in turn (the order
  rotated each round), repeated; the throughput is env steps trained per second (bodies trained,
  not repeats born from an earlier body's result) between the first job and the last birth, and
  `ratio` the median of each window's throughput over the free-running run of the same round.
Run: python bench/window.py [--profiles demo paper] [--trainers 2 16 72 144] [--seeds 5]
     python bench/window.py --real [--trainers 2] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml
from repeats import simulate

from derl.evolution import load_profile
from derl.unimal import sample_population

REPO = Path(__file__).resolve().parents[1]
FACTORS = (2, 4)
REAL_PROFILE = {
    "profile": "smoke",
    "population": 16,
    "tournament": 4,
    "total": 48,
    "train_steps": 16384,
    "num_envs": 16,
    "eval_top": 0,
    "eval_tasks": [],
}


def windows(trainers: int, population: int) -> dict[str, int]:
    """Free-running and each factor's window that a population of `population` allows (W < P)."""
    chosen = {"free": 0}
    for factor in FACTORS:
        if factor * trainers < population:
            chosen[f"{factor}x"] = factor * trainers
    return chosen


def simulated(profiles: list[str], trainer_counts: list[int], seeds: int) -> None:
    for profile in profiles:
        config = load_profile(profile, [("timing", "window")])  # W = 0 is measured too
        initial = sample_population(config.population, np.random.default_rng([config.seed, 0]))
        for trainers in trainer_counts:
            chosen = windows(trainers, config.population)
            use: dict[str, list[float]] = {}
            for name, w in chosen.items():
                windowed = config.model_copy(update={"in_flight": w})
                use[name] = [
                    simulate(windowed, initial, trainers, "random", seed, hold=True)["utilisation"]
                    for seed in range(seeds)
                ]
            result = {
                "measure": "simulated",
                "profile": profile,
                "population": config.population,
                "total": config.total,
                "trainers": trainers,
                "windows": chosen,
                "utilisation": {k: round(statistics.median(v), 4) for k, v in use.items()},
                "ratio": ratios(use),
            }
            print(json.dumps(result), flush=True)


def ratios(measured: dict[str, list[float]]) -> dict[str, float]:
    """Each window's median ratio to free-running over the paired measurements."""
    free = measured["free"]
    return {
        name: round(statistics.median(a / b for a, b in zip(values, free, strict=True)), 4)
        for name, values in measured.items()
        if name != "free"
    }


def real_run(folder: Path, trainers: int, in_flight: int, port: int) -> float:
    """Env steps trained per second of one real run, between its first job and its last birth."""
    from derl.messages import Birth, TrainJob
    from derl.nodes.journal.segments import read_logged, segments

    profile = folder / "profile.yaml"
    profile.write_text(yaml.safe_dump({**REAL_PROFILE, "in_flight": in_flight}))
    endpoint = f"tcp/127.0.0.1:{port}"
    run = f"window{in_flight}"
    coordinator = ["coordinator", "--profile", str(profile), "--run-dir", str(folder / "run")]
    argvs = [[*coordinator, "--run", run, "--listen", endpoint]]
    for k in range(trainers):
        argvs.append(["trainer", "--run", run, "--connect", endpoint, "--name", f"t{k}"])
    derl = [sys.executable, "-m", "derl.nodes.cli"]
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    nodes = [subprocess.Popen([*derl, *argv], **quiet) for argv in argvs]
    try:
        if nodes[0].wait(timeout=1800) != 0:
            raise RuntimeError(f"the coordinator of {folder} failed")
    finally:
        for node in nodes:
            node.terminate()
        for node in nodes:
            node.wait(timeout=30)
    jobs, births, trained = [], [], 0
    for segment in segments(folder / "run"):
        for logged in read_logged(segment):
            msg = logged.message
            if isinstance(msg, TrainJob):
                jobs.append(logged.log_time)
            elif isinstance(msg, Birth):
                births.append(logged.log_time)
                trained += msg.repeat_of is None
    return trained * REAL_PROFILE["train_steps"] / ((max(births) - min(jobs)) / 1e9)


def real(trainers: int, rounds: int, port: int) -> None:
    chosen = windows(trainers, REAL_PROFILE["population"])
    rates: dict[str, list[float]] = {name: [] for name in chosen}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(rounds):
            names = list(chosen)
            for name in names[k % len(names) :] + names[: k % len(names)]:
                w = chosen[name]
                folder = Path(tmp) / f"{k}-{name}"
                folder.mkdir()
                rates[name].append(real_run(folder, trainers, w, port))
    result = {
        "measure": "real",
        "profile": REAL_PROFILE,
        "trainers": trainers,
        "windows": chosen,
        "steps_per_s": {k: [round(r) for r in v] for k, v in rates.items()},
        "ratio": ratios(rates),
    }
    print(json.dumps(result), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profiles", nargs="+", default=["demo", "paper"])
    parser.add_argument("--trainers", type=int, nargs="+", default=[2, 16, 72, 144])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--real", action="store_true", help="real processes (--trainers: one)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--port", type=int, default=7591)
    args = parser.parse_args()
    if args.real:
        real(args.trainers[0], args.rounds, args.port)
    else:
        simulated(args.profiles, args.trainers, args.seeds)


if __name__ == "__main__":
    main()
