"""How much the timing matters: the coordinator's evolution at paper scale in the window timing
against the cluster timing (`derl.evolution.timing`); prints JSON.

``--calibrate``: the cluster timing's coefficients (`TrainingTime`) measured on this machine:
real FT trainings (`derl.lifetime.learn`, one thread) of `--bodies` bodies of as many limb counts
(drawn as initial bodies are: 1 to 6 limbs at 6), their CPU
seconds fitted as env steps x `step_s` + constraint rows x `row_s` (least squares, both at least
0), and `episode_s`, what the released code paid at every reset, its model rebuilt from XML: the
median CPU time of building a body's model in its world (`UnimalEnv`, one copy).

Default: per seed, the paper's profile (P 576, T 4, W 288, 4,000 births) run by the coordinator's
own state machine (`derl.evolution.Evolution`: tournaments, breeding, repeats born with their
body's result) in each timing, with W simulated trainers. A body's training is not run:
- its fitness is a surrogate, a uniform draw from its `body_hash` (no shape is fitter than
  another: any trend in the bodies comes from the timing, not from selection on fitness);
- its counts are a surrogate too: constraint rows per env step linear in its limb count
  (`ROWS_PER_STEP`, fitted to the calibration's trainings), times the paper's 5M steps; its
  episodes 5M / 1,000 (every episode its full length: the same for every body); its duration
  `TrainingTime.duration` of those with the profile's (calibrated) coefficients. So a limb costs
  training time, as in the released code, and nothing else does.
Per run: the mean limb count and mass of the first and last quarter of the births in child order
and their change (the trend), the share of the last P births that descend from the most common
initial body (its lineage) and the lineages alive among them, and the time to the last birth
(`hours`: with W simulated trainers whose trainings take their virtual durations, in either
timing; in the cluster timing they wait for the virtual clock, whose own time to the last birth,
the released cluster's, is about `utilisation` x `hours`). Per timing the mean over seeds with a
95 % t-interval, and cluster - window and released - cluster paired by seed.
And the cluster timing with the released end (`end: released`, as `tools/evolution.py`'s
`wait_or_kill` drops the trainings in flight when the last body is saved: `Evolution.released_end`):
the same measures over the N bodies it keeps, and the children it dropped (`dropped`), their mean
limb count (`dropped_limbs`) against that of the last quarter kept.
Also the parallelism the cluster timing leaves real trainers: with R trainers whose trainings take
their virtual durations, the trainers' busy time over R x the run's duration (`utilisation`), at
R = W / 4, W / 2 and W, for the paper's W and the demo's (P 16, W 8, 128 births).
Run: python bench/timing.py [--seeds 3] [--births 4000]
     python bench/timing.py --calibrate [--steps 32768] [--bodies 6]
"""

from __future__ import annotations

import argparse
import hashlib
import heapq
import json
import statistics
import sys
import time
from collections import Counter, deque

import numpy as np
from scipy import optimize, stats

from derl.envs import EnvConfig, UnimalEnv, make_task
from derl.evolution import Evolution, EvolutionConfig, load_profile
from derl.unimal import Genome, body_hash, sample_population
from derl.unimal.mjcf import agent_spec

WORLD = "ft"
EPISODE_STEPS = EnvConfig().episode_steps
FIELDS = ("limbs", "env_steps", "episodes", "constraint_rows", "cpu_s")
ROWS_PER_STEP = (0.76, 0.90)
"""Constraint rows per env step of a training: (intercept, per limb), fitted to `--calibrate`'s
trainings (its ``rows_per_step``)."""


def calibrate(steps: int, bodies: int) -> dict[str, object]:
    """`TrainingTime`'s coefficients measured on this machine (see the module)."""
    import torch

    from derl.lifetime import learn, ppo_config

    torch.set_num_threads(1)
    rng = np.random.default_rng(11)
    chosen: dict[int, Genome] = {}
    for _ in range(20):  # bodies of as many limb counts as asked (initial ones have 1 to 6)
        for genome in sample_population(8, rng):
            chosen.setdefault(len(genome.limbs), genome)
        if len(chosen) >= bodies:
            break
    config = ppo_config(WORLD, steps, 1409, num_envs=32)
    rows, builds = [], []
    for genome in list(chosen.values())[:bodies]:
        start = time.process_time()
        summary, _ = learn(genome, WORLD, config)
        cpu = time.process_time() - start
        start = time.process_time()
        UnimalEnv(genome, make_task(WORLD), EnvConfig(num_envs=1))
        builds.append(time.process_time() - start)
        rows.append((len(genome.limbs), summary.env_steps, summary.episodes,
                     summary.constraint_rows, cpu))  # fmt: skip
        print(json.dumps(dict(zip(FIELDS, rows[-1], strict=True))), file=sys.stderr, flush=True)
    a = np.array([[r[1], r[3]] for r in rows], dtype=float)
    b = np.array([r[4] for r in rows])
    (step_s, row_s), _ = optimize.nnls(a, b)
    fitted = a @ np.array([step_s, row_s])
    per_step = np.array([r[3] / r[1] for r in rows])
    limbs = np.array([r[0] for r in rows], dtype=float)
    slope, intercept = np.polyfit(limbs, per_step, 1)
    return {
        "trainings": [dict(zip(FIELDS, r, strict=True)) for r in rows],
        "step_s": float(step_s),
        "row_s": float(row_s),
        "episode_s": statistics.median(builds),
        "r2": float(1 - np.sum((b - fitted) ** 2) / np.sum((b - b.mean()) ** 2)),
        "rows_per_step": [float(intercept), float(slope)],
        "max_error": float(np.max(np.abs(b - fitted) / b)),
    }


class Probe:
    """A body's surrogate counts and its descriptors (see the module), kept per body."""

    def __init__(self) -> None:
        self.known: dict[str, tuple[float, float, int]] = {}  # hash -> rows/step, mass, limbs

    def __call__(self, genome: Genome) -> tuple[float, float, int]:
        key = body_hash(genome)
        if key not in self.known:
            mass = float(agent_spec(genome).compile().body_mass.sum())
            limbs = len(genome.limbs)
            self.known[key] = (ROWS_PER_STEP[0] + ROWS_PER_STEP[1] * limbs, mass, limbs)
        return self.known[key]


def surrogate_fitness(genome: Genome) -> float:
    """A uniform draw from the body's hash: no shape is fitter than another."""
    return int(hashlib.sha256(body_hash(genome).encode()).hexdigest()[:12], 16) / 16**12


def run(
    config: EvolutionConfig, initial: list[Genome], probe: Probe, trainers: int
) -> dict[str, object]:
    """One evolution with `trainers` simulated trainers (see the module); its measures."""
    evolution = Evolution(config, initial)
    steps = config.training_ppo().total_steps
    episodes = steps // EPISODE_STEPS

    def work(genome: Genome) -> tuple[int, int]:
        return episodes, round(probe(genome)[0] * steps)

    def duration(genome: Genome) -> float:
        return config.training_time.duration(steps, *work(genome)) / 1e6

    waiting = deque(child.name for child in evolution.initial)
    running: list[tuple[float, int, str]] = []  # (finish, child number, child)
    now = busy = 0.0
    idle = trainers

    def next_child() -> str | None:
        if waiting:
            return waiting.popleft()
        if config.end == "all" and evolution.settled + len(running) >= config.total:
            return None
        decided = evolution.tournament()
        if decided is None:
            return None
        evolution.record(decided)
        return decided.name

    def dispatch() -> None:
        nonlocal idle, busy
        while idle and (name := next_child()) is not None:
            body, _ = evolution.body(name)
            earlier = evolution.repeat(name)
            if earlier is not None:  # born at once with its body's result, as the coordinator
                evolution.birth(name, evolution.fitness[earlier], body, earlier, work(body))
                continue
            took = duration(body)
            busy += took
            idle -= 1
            heapq.heappush(running, (now + took, evolution.index[name], name))

    dispatch()
    while running:
        now, _, name = heapq.heappop(running)
        idle += 1
        body = evolution.genomes[name]
        evolution.birth(name, surrogate_fitness(body), body, None, work(body))
        if (drop := evolution.released_end()) is not None:
            evolution.drop(drop)  # what trains still is dropped: the run is over
            break
        dispatch()
    assert evolution.complete
    born = sorted(evolution.born, key=lambda m: evolution.index[m.agent])
    quarter = len(born) // 4

    def mean(members: list, k: int) -> float:
        return statistics.fmean(probe(evolution.genomes[m.agent])[k] for m in members)

    def founder(agent: str) -> str:
        while (parent := evolution.parents[agent]) is not None:
            agent = parent
        return agent

    last = Counter(founder(m.agent) for m in born[-config.population :])
    measures = {"hours": now / 3600, "utilisation": busy / (trainers * now)}
    for k, name in ((2, "limbs"), (1, "mass")):
        first, end = mean(born[:quarter], k), mean(born[-quarter:], k)
        measures.update({f"{name}_first": first, f"{name}_last": end, f"{name}_trend": end - first})
    measures["top_lineage_share"] = last.most_common(1)[0][1] / config.population
    measures["lineages"] = len(last)
    if evolution.dropped is not None:  # the released end (see the module)
        dropped = sorted(evolution.dropped)
        measures["dropped"] = len(dropped)
        measures["dropped_limbs"] = statistics.fmean(
            probe(evolution.genomes[c])[2] for c in dropped
        )
        measures["kept_limbs"] = measures["limbs_last"]
    return measures


def interval(values: list[float]) -> dict[str, float]:
    """Mean and 95 % t-interval."""
    mean = statistics.fmean(values)
    if len(values) < 2:
        return {"mean": mean}
    half = stats.t.ppf(0.975, len(values) - 1) * statistics.stdev(values) / len(values) ** 0.5
    return {"mean": mean, "low": mean - half, "high": mean + half}


def compare(seeds: int, births: int) -> dict[str, object]:
    probe = Probe()
    settings = {"window": [("timing", "window")], "cluster": [("timing", "cluster")],
                "released": [("timing", "cluster"), ("end", "released")]}  # fmt: skip
    runs: dict[str, list[dict[str, object]]] = {name: [] for name in settings}
    for seed in range(seeds):
        base = load_profile("paper", total=births, seed=seed)
        initial = sample_population(base.population, np.random.default_rng([seed, 0]))
        for timing in runs:
            config = load_profile("paper", settings[timing], total=births, seed=seed)
            start = time.perf_counter()
            measures = run(config, initial, probe, config.in_flight)
            measures["seconds"] = time.perf_counter() - start
            runs[timing].append(measures)
    summary: dict[str, object] = {
        t: {k: interval([r[k] for r in rs]) for k in rs[0] if k != "seconds"}
        for t, rs in runs.items()
    }
    keys = [k for k in runs["window"][0] if k != "seconds"]
    for a, b in (("cluster", "window"), ("released", "cluster")):
        summary[f"{a}_minus_{b}"] = {
            k: interval([x[k] - y[k] for x, y in zip(runs[a], runs[b], strict=True)]) for k in keys
        }
    return {"seeds": seeds, "births": births, "rows_per_step": ROWS_PER_STEP, "runs": runs,
            "summary": summary, "parallelism": parallelism(probe)}  # fmt: skip


def parallelism(probe: Probe) -> list[dict[str, object]]:
    """The cluster timing's trainer utilisation at R = W/4, W/2, W (see the module)."""
    out = []
    for profile, births in (("demo", 128), ("paper", 1200)):
        config = load_profile(profile, [("timing", "cluster")], total=births)
        initial = sample_population(config.population, np.random.default_rng([0, 0]))
        for trainers in (config.in_flight // 4, config.in_flight // 2, config.in_flight):
            measured = run(config, initial, probe, trainers)
            out.append({"profile": profile, "births": births, "W": config.in_flight,
                        "trainers": trainers, "utilisation": measured["utilisation"]})  # fmt: skip
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calibrate", action="store_true")
    parser.add_argument("--steps", type=int, default=32768, help="env steps per calibration")
    parser.add_argument("--bodies", type=int, default=6)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--births", type=int, default=4000)
    args = parser.parse_args()
    if args.calibrate:
        print(json.dumps(calibrate(args.steps, args.bodies), indent=1))
    else:
        print(json.dumps(compare(args.seeds, args.births), indent=1))


if __name__ == "__main__":
    main()
