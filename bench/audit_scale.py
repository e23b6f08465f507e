"""What the audit rules catch at the paper's scale: 288 trainers, 4,000 births, one liar.

`bench/audit.py` drives the coordinator's own handlers, which breed every body and check every
policy: minutes per thousand births. This bench plays the same run's decisions in simulated time
with the same pieces: the run's `Evolution` (pool, tournaments, `correct`) for who is bred from
whom, and the audit rules `nodes.coordinator.audits.Rules` and `Record` for which children are
trained twice; the queue follows `EvolutionState` (a child that waits for another identity goes
first, a disagreement waits for a third identity, the liar is quarantined and its unchecked births
trained again first, its jobs taken back; once they are, every tournament decided after the first
of them that was a lie is undone and decided again, `Evolution.undo`, the same body bred again
born from the undone child's training at once). Bodies are not bred: a child's honest fitness is its
parent's honest fitness plus a draw, N(-2, 10), from 100 + N(0, 10) for an initial body (a model:
the audits' top-rank rule sees the ranks this makes), drawn from the child and its parent (a
body is its ancestors' bred with its tournaments' seeds), and a training lasts U(0.5, 1.5).

One trainer lies on a share of its reports (`--rates`, drawn per child) with 1.25 x + 1 of the
honest fitness (the issue's liar, real checkpoints). Per run (JSON, one line): whether the liar was
caught, the births when it was, its lies and those born from (before the catch), the births
undone, births whose parent differs from the honest run's at the end (swayed), trainings beyond
one per birth, the duration over the unaudited run's, and whether the fingerprint equals the
honest run's; then a summary per rate.
Run: python bench/audit_scale.py [--seeds 20] [--first-seed 0] [--rates 1 0.1 0.01]
[--trainers 288] [--set KEY VALUE]
"""

from __future__ import annotations

import argparse
import hashlib
import heapq
import json
import random
import statistics
from collections import deque
from dataclasses import dataclass, field

from derl.evolution import Evolution, EvolutionConfig, load_profile
from derl.evolution.fingerprint import fingerprint
from derl.nodes.coordinator.run.audits import Record, Rules
from derl.unimal import Genome
from derl.unimal.space import DENSITIES

HEAD = Genome(head_density=DENSITIES[0], limb_density=DENSITIES[0])  # every body: not bred


def _draw(*what: object) -> random.Random:
    return random.Random(hashlib.sha256(" ".join(map(str, what)).encode()).digest())


@dataclass
class Run:
    """One run in simulated time (see the module); `rate` 0: the liar is honest."""

    config: EvolutionConfig
    trainers: int
    rate: float
    honest: dict[tuple[str, ...], float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.rules = Rules.of(self.config)
        self.evolution = Evolution(self.config, [HEAD] * self.config.population)
        self.names = [f"t{k}" for k in range(self.trainers)]
        self.liar = self.names[-1]
        self.queue: deque[str] = deque(c.name for c in self.evolution.initial)
        self.retraining: set[str] = set()
        self.trials: dict[str, list[tuple[str, float]]] = {}
        self.auditing: set[str] = set()
        self.records: dict[str, Record] = {}
        self.born_from: dict[str, tuple[str, bool]] = {}  # child -> (identity, checked)
        self.quarantined: set[str] = set()
        self.running: list[tuple[float, int, str, str]] = []  # (finish, n, trainer, child)
        self.in_training: dict[str, str] = {}  # trainer -> child
        self.idle: deque[str] = deque(self.names)
        self.trainings = self.lies = self.lies_born = self.lies_audited = self.undone = 0
        self.caught_at: int | None = None
        self.decided_before: dict[str, int] = {}  # child -> tournaments decided before its birth
        self.undo_from: int | None = None  # the first tournament to decide again
        self.kept: dict[tuple[str, ...], float] = {}  # an undone child's `body` -> its fitness

    def fitness(self, child: str) -> float:
        body = self.body(child)
        if body not in self.honest:
            parent = self.evolution.parents[child]
            rng = _draw(self.config.seed, child, parent)
            base = 100.0 if parent is None else self.fitness(parent) - 2.0
            self.honest[body] = base + rng.gauss(0.0, 10.0)
        return self.honest[body]

    def body(self, child: str) -> tuple[str, ...]:
        """What a child's body (and so its honest fitness) is a function of in this model: its
        name and its ancestors' (each body is its parent's bred with its tournament's seed)."""
        parent = self.evolution.parents[child]
        return (child,) if parent is None else (child, *self.body(parent))

    def tried_by(self, child: str) -> set[str]:
        if child in self.retraining:
            return {self.born_from[child][0]}
        return {who for who, _ in self.trials.get(child, [])}

    def assign(self, trainer: str, now: float) -> bool:
        child = next((c for c in self.queue if trainer not in self.tried_by(c)), None)
        if child is not None:
            self.queue.remove(child)
        while child is None:
            pending = self.retraining or self.undo_from is not None  # a lie may be undone
            if pending or len(self.evolution.parents) >= self.config.total:
                return False
            decided = self.evolution.tournament()
            if decided is None:
                return False
            self.evolution.record(decided)
            kept = self.kept.get(self.body(decided.name))
            if kept is None:
                child = decided.name
            else:  # the same body bred again: born from the undone child's training
                self.born(decided.name, "kept", kept, [])
                self.born_from[decided.name] = ("kept", True)
        self.in_training[trainer] = child
        self.trainings += 1
        finish = now + _draw(self.config.seed, "time", self.trainings).uniform(0.5, 1.5)
        heapq.heappush(self.running, (finish, self.trainings, trainer, child))
        return True

    def report(self, trainer: str, child: str) -> None:
        del self.in_training[trainer]
        value = self.fitness(child)
        lie = trainer == self.liar and _draw(self.config.seed, "lie", child).random() < self.rate
        if lie:
            value, self.lies = 1.25 * value + 1.0, self.lies + 1
        if child in self.retraining:
            self.retraining.discard(child)
            decided = self.decided_before[child]  # a lie born from: decide again after it
            if value != self.evolution.fitness[child] and decided < self.evolution.iterations:
                self.undo_from = min(decided, decided if self.undo_from is None else self.undo_from)
            self.evolution.correct(child, value)
            if not self.retraining and self.undo_from is not None:
                self.undo()
            return
        record = self.records.setdefault(trainer, Record())
        first = child not in self.trials
        if first and self.rules.audits(
            child, trainer, value, record, lambda: self.evolution.population
        ):
            self.auditing.add(child)
        record.reports += 1
        if child not in self.auditing:
            self.born(child, trainer, value, [])
            return
        self.lies_audited += lie
        trials = self.trials.setdefault(child, [])
        trials.append((trainer, value))
        if len(trials) == 2 and trials[0][1] == trials[1][1]:
            self.born(child, trials[0][0], trials[0][1], trials)
        elif len(trials) < 3:
            self.queue.appendleft(child)
        else:
            (a, fa), (b, fb), (c, fc) = trials
            if fc in (fa, fb):
                self.born(child, c, fc, trials)
                self.quarantine(b if fc == fa else a)
            else:  # none alike: nobody blamed, every record starts again
                self.born(child, c, fc, trials)

    def born(self, child: str, who: str, value: float, trials: list[tuple[str, float]]) -> None:
        self.trials.pop(child, None)
        self.auditing.discard(child)
        self.born_from[child] = (who, len(trials) > 1)
        self.decided_before[child] = self.evolution.iterations
        self.lies_born += value != self.fitness(child)
        self.evolution.birth(child, value, HEAD)
        agreed = [w for w, v in trials if v == value]
        for w, _ in trials:
            record = self.records.setdefault(w, Record())
            if len(agreed) < 2:
                record.agreed = record.reports = 0
            elif w in agreed:
                record.agreed += 1

    def quarantine(self, liar: str) -> None:
        self.quarantined.add(liar)
        self.caught_at = len(self.evolution.born)
        for reports in self.trials.values():
            reports[:] = [(w, v) for w, v in reports if w != liar]
        retrain = [c for c, (w, checked) in self.born_from.items() if w == liar and not checked]
        for child in reversed(retrain):
            self.retraining.add(child)
            self.queue.appendleft(child)
        if liar in self.in_training:
            self.queue.appendleft(self.in_training.pop(liar))
            self.running = [r for r in self.running if r[2] != liar]
            heapq.heapify(self.running)

    def undo(self) -> None:
        """Every tournament from `undo_from` on is decided again (`Evolution.undo`): each born
        child's (honest) result is kept for the same body bred again, its trainings in flight
        end, and its trainer is idle."""
        evolution, iteration = self.evolution, self.undo_from
        assert iteration is not None
        for child in evolution.decided_from(iteration):
            if child in evolution.fitness:
                self.kept[self.body(child)] = evolution.fitness[child]
        gone = set(evolution.undo(iteration))
        self.undone += sum(child in self.born_from for child in gone)
        self.undo_from = None
        self.queue = deque(c for c in self.queue if c not in gone)
        for child in gone:
            self.born_from.pop(child, None)
            self.trials.pop(child, None)
            self.auditing.discard(child)
        for trainer, child in list(self.in_training.items()):
            if child in gone:
                del self.in_training[trainer]
                self.idle.append(trainer)
        self.running = [r for r in self.running if r[3] not in gone]
        heapq.heapify(self.running)

    def play(self) -> float:
        """The run to its end; its duration."""
        now, idle = 0.0, self.idle
        while not (self.evolution.complete and not self.retraining):
            for _ in range(len(idle)):
                trainer = idle.popleft()
                if trainer not in self.quarantined and not self.assign(trainer, now):
                    idle.append(trainer)
            if not self.running:
                raise RuntimeError(f"stalled at {len(self.evolution.born)} born")
            now, _, trainer, child = heapq.heappop(self.running)
            self.report(trainer, child)
            idle.append(trainer)
        return now

    def births(self) -> dict[str, tuple[str | None, float]]:
        return {m.agent: (m.parent, m.fitness) for m in self.evolution.born}

    def print(self) -> str:
        generation: dict[str, int] = {}
        for m in sorted(self.evolution.born, key=lambda m: self.evolution.index[m.agent]):
            generation[m.agent] = 0 if m.parent is None else generation[m.parent] + 1
        facts = [(m.agent, m.parent, generation[m.agent], m.fitness, HEAD)
                 for m in self.evolution.born]  # fmt: skip
        return fingerprint(facts)


def seed_runs(
    config: EvolutionConfig, trainers: int, rates: list[float], seed: int
) -> list[dict[str, object]]:
    """The runs of one seed: honest, unaudited, and one with a liar at each of `rates`."""
    config = config.model_copy(update={"seed": seed})
    honest = Run(config, trainers, 0.0)
    unaudited = Run(config.model_copy(update={"audit": 0.0}), trainers, 0.0)
    duration, unaudited_duration = honest.play(), unaudited.play()
    truth, results = honest.births(), []
    for rate in rates:
        lying = Run(config, trainers, rate)
        lying_duration = lying.play()
        births = lying.births()
        results.append({
            "rate": rate,
            "seed": seed,
            "lies": lying.lies,
            "lies_audited": lying.lies_audited,
            "caught": lying.caught_at is not None,
            "caught_after_births": lying.caught_at,
            "lies_born": lying.lies_born,
            "undone": lying.undone,
            "swayed": sum(births[c][0] != truth[c][0] for c in births),
            "extra_trainings": round(lying.trainings / len(births) - 1, 4),
            "honest_extra_trainings": round(honest.trainings / len(truth) - 1, 4),
            "honest_duration_ratio": round(duration / unaudited_duration, 4),
            "duration_ratio": round(lying_duration / unaudited_duration, 4),
            "same_fingerprint": lying.print() == honest.print(),
        })  # fmt: skip
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profile", default="paper")
    parser.add_argument("--trainers", type=int, default=288)
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--rates", type=float, nargs="+", default=[1.0, 0.1, 0.01])
    parser.add_argument("--set", nargs=2, action="append", default=[], metavar=("KEY", "VALUE"),
                        help="a profile key changed, e.g. --set audit_first 2")  # fmt: skip
    args = parser.parse_args()
    changes = {key: json.loads(value) for key, value in args.set}
    base = load_profile(args.profile, [("timing", "window")])
    base = base.model_copy(update={"eval_top": 0, **changes})
    by_rate: dict[float, list[dict[str, object]]] = {}
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for run in seed_runs(base, args.trainers, args.rates, seed):
            by_rate.setdefault(run["rate"], []).append(run)
            print(json.dumps(run), flush=True)
    for rate, runs in by_rate.items():
        lied = [r for r in runs if r["lies"]]
        lies = sum(r["lies"] for r in runs)
        print(json.dumps({
            "summary": rate, "profile": args.profile, "trainers": args.trainers,
            "timing": base.timing, "audit": base.audit, "audit_first": base.audit_first,
            "audit_top": base.audit_top,
            "runs": len(runs), "lied": len(lied),
            "caught_of_lied": f"{sum(r['caught'] for r in lied)}/{len(lied)}",
            "lies_audited": f"{sum(r['lies_audited'] for r in runs)}/{lies}",
            "lies_born": sum(r["lies_born"] for r in runs),
            "undone_median": statistics.median(r["undone"] for r in lied) if lied else 0,
            "swayed_median": statistics.median(r["swayed"] for r in runs),
            "same_fingerprint": f"{sum(r['same_fingerprint'] for r in runs)}/{len(runs)}",
            "extra_trainings": statistics.median(r["honest_extra_trainings"] for r in runs),
            "duration_ratio": statistics.median(r["honest_duration_ratio"] for r in runs),
        }), flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
