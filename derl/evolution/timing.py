"""The cluster timing: the released code's 288 workers simulated in virtual time, so that bodies
that train fast join the population sooner, and the run is still a function of its seed.

In the released code each worker trains its share of the initial bodies, then, whenever its own
training ends, draws a tournament from the P bodies that finished most recently (by file mtime)
and trains the child. `ClusterClock` does the same with W virtual workers (the profile's
`in_flight`): initial body k is worker k mod W's (each trains its share one after the other from
time 0), and tournament j's child is bred at the j-th moment a worker comes free, from the P born
bodies that finished last by then, in the order they finished, and trained by that worker. A
training's virtual duration is a deterministic function of what it did (`TrainingTime`: its env
steps, its episodes, the constraint rows MuJoCo solved), counted by the trainer and carried in
its report and its `Birth`, so a resumed coordinator rebuilds the same clock from the journal.
Times are whole microseconds: equal times are exact, and are ordered by the child's number.
The released end (`end: released`): a worker breeds only while fewer than N bodies finished,
and the run keeps the N that finished first (`nth_finish`); what was in flight then is dropped.

A real trainer may train any child in flight; the clock only says when the next child may be
bred: once every child that could finish before the next worker comes free is known. Every
training lasts at least its fixed part (`TrainingTime.least`, its env steps' share), so a child
whose training is not done yet counts only if it started more than that before.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

MICROSECONDS = 1_000_000


class TrainingTime(BaseModel):
    """A training's virtual duration: env steps x `step_s` + episodes x `episode_s` (the released
    code rebuilt the simulation at every reset) + constraint rows x `row_s`, calibrated once on
    this repository's machine (`bench/timing.py --calibrate`; docs/fidelity.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    step_s: float = Field(
        5.7e-5, gt=0, description="seconds per env step (policy, PPO update and physics)"
    )
    episode_s: float = Field(
        0.0054, ge=0, description="seconds per episode: the released code rebuilt its model then"
    )
    row_s: float = Field(
        1.4e-5, ge=0, description="seconds per constraint row solved (summed over control steps)"
    )

    def duration(self, env_steps: int, episodes: int, constraint_rows: int) -> int:
        """A training's virtual duration, microseconds."""
        seconds = env_steps * self.step_s + episodes * self.episode_s
        return round(MICROSECONDS * (seconds + constraint_rows * self.row_s))

    def least(self, env_steps: int) -> int:
        """The least duration of a training of `env_steps` (no episode, no constraint)."""
        return self.duration(env_steps, 0, 0)


@dataclass
class _Worker:
    """A virtual worker's children since it last came free: `start` the first one's start (the
    others follow one another: a worker's share of the initial bodies)."""

    start: int
    children: list[int]
    retired: bool = False  # came free before any body was born: it breeds no more


class ClusterClock:
    """Children's virtual starts and finishes on `workers` virtual workers (see the module):
    `done` tells it a child's duration, `breeding(j)` says when and from which finished children
    tournament j's child is bred, once that is known."""

    def __init__(self, workers: int, initial: int, population: int, least: int) -> None:
        """`initial`: the P initial bodies (children 0..P-1); `population`: the P most recent
        finishes a tournament draws from; `least`: every training's least duration."""
        self.population, self.least, self.initial = population, least, initial
        self.workers = [_Worker(0, list(range(w, initial, workers))) for w in range(workers)]
        self.duration: dict[int, int] = {}  # child -> its virtual duration, once known
        self.finish: dict[int, int] = {}  # child -> its virtual finish, once known
        self.born: set[int] = set()
        self.finished: list[tuple[int, int]] = []  # (finish, child) of born children, ascending
        self.events: list[tuple[int, int]] = []  # breeding j: (time, the child that finished)
        self._next: tuple[int, int, int] | None = None  # the next breeding, once certain

    def done(self, child: int, duration: int, born: bool) -> None:
        """`child`'s training took `duration` (a child given up: the least); `born`: it joins
        the population when it finishes."""
        if child in self.duration:
            return
        self.duration[child] = duration
        if born:
            self.born.add(child)
        self._next = None
        for worker in self.workers:
            if child in worker.children:
                self._finishes(worker)

    def _finishes(self, worker: _Worker) -> None:
        """The finishes of `worker`'s children that are known now."""
        time = worker.start
        for child in worker.children:
            if child not in self.duration:
                return
            time += self.duration[child]
            if child not in self.finish:
                self.finish[child] = time
                if child in self.born:
                    bisect.insort(self.finished, (time, child))

    def breeding(self, iteration: int) -> tuple[int, list[int], int] | None:
        """When tournament `iteration`'s child is bred (virtual microseconds), the P children
        it draws from (those that finished last by then, oldest first) and how many born
        children finished by then; None while not known. Every earlier tournament's child is
        taken to be bred (`Evolution.record` or given up): child P + j starts on the worker that
        came free at breeding j."""
        while len(self.events) < iteration:
            if not self._assign():
                return None
        event = self._peek()
        if event is None:
            return None
        time, last, _ = event
        end = bisect.bisect_right(self.finished, (time, last))
        pool = [child for _, child in self.finished[max(0, end - self.population) : end]]
        return time, pool, end

    def nth_finish(self, n: int) -> tuple[int, int] | None:
        """The `n`-th finish of a born child (time, child), once no finish still unknown could
        come before it (no child is bred before it: the caller knows); None before."""
        if len(self.finished) < n:
            return None
        nth = self.finished[n - 1]
        _, bound = self._scan()
        return nth if bound is None or bound > nth else None

    def _assign(self) -> bool:
        """Breeding number len(events) happens: its child starts on the worker that came free."""
        event = self._peek()
        if event is None:
            return False
        time, last, w = event
        self.events.append((time, last))
        self.workers[w] = _Worker(time, [self.initial + len(self.events) - 1])
        self._finishes(self.workers[w])  # its child may be done already
        self._next = None
        return True

    def _peek(self) -> tuple[int, int, int] | None:
        """The next moment a worker comes free (time, the child it finished, the worker), once
        no child whose finish is unknown could finish before it (or at it, numbered lower)."""
        if self._next is not None:
            return self._next
        best, bound = self._scan()
        if best is None or (bound is not None and bound <= best[:2]):
            return None
        if not self.finished or self.finished[0] > best[:2]:  # none born by then: no draw
            self.workers[best[2]].retired = True
            return self._peek()
        self._next = best
        return best

    def _scan(self) -> tuple[tuple[int, int, int] | None, tuple[int, int] | None]:
        """The first worker to come free of those whose children's durations are all known
        (time, its last child, the worker), and the earliest a finish not known yet can be
        (time, child: each unknown duration taken as the least)."""
        best: tuple[int, int, int] | None = None
        bound: tuple[int, int] | None = None
        for w, worker in enumerate(self.workers):
            if worker.retired:
                continue
            time, known = worker.start, True
            for child in worker.children:
                step = self.duration.get(child)
                if step is None:
                    known = False
                time += self.least if step is None else step
                if not known and (bound is None or (time, child) < bound):
                    bound = (time, child)
            if known and (best is None or (time, worker.children[-1]) < best[:2]):
                best = (time, worker.children[-1], w)
        return best, bound
