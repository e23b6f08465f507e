"""`derl monitor`: a live terminal view of one run, redrawn twice a second.

It taps ``derl/<run>/**`` through a ring (`nodes.tools.topic.Tap`) and follows the run's liveliness
tokens, so a slow terminal never slows the run: the tap's thread only validates and queues, and
the main loop folds the queue into a `RunView` and draws it with rich: a header (bodies born of
the target, best fitness and agent, steps/s, evaluations, repeats, rejections), the workers (role,
job, body, env steps, recent return, steps/s, last heard), the latest births (parent, mutation,
fitness, node or the earlier body a repeat took its result from) and a sparkline of fitness over
births. Births come from the coordinator's birth stream (``births/*``, the journal's Birth
records), folded by `nodes.journal.history.RunHistory`, the one reading of a run every tool
shares; a monitor started mid-run first asks the coordinator for the recent births (a Zenoh
query), so it is complete without the journal. It works on replayed logs too: when no RunStatus
is heard (a journal holds none), the best comes from the births.
"""

from __future__ import annotations

import logging
import statistics
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from itertools import pairwise

import zenoh
from rich.console import Console, Group
from rich.live import Live
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from derl.messages import (
    Ack,
    Birth,
    EvalJob,
    EvalResult,
    FitnessReport,
    KeySpace,
    MessageBase,
    PopulationSnapshot,
    Reject,
    RunStatus,
    TrainJob,
    TrainProgress,
    WorkerReady,
)
from derl.messages.dispatch import Handler, handles
from derl.messages.keys import REMEMBERED_BIRTHS
from derl.nodes.journal.history import RunHistory
from derl.nodes.runtime.bus import Bus, ZenohOptions, open_session
from derl.nodes.tools.topic import DISCOVERY_S, Checker, Tap, ask, choose_run

REFRESH_S = 0.5
RECENT_BIRTHS = 8
MAX_WORKER_ROWS = 24
SPARK_WIDTH = 64
SPARK = "▁▂▃▄▅▆▇█"
PIPED_WIDTH = 160
"""Columns of the view when it goes to a file or a pipe (`--once` in a script)."""
QUEUE = 10_000
"""Messages waiting to be drawn; beyond it the oldest are dropped (the view is only a view)."""


def sparkline(values: list[float], width: int = SPARK_WIDTH) -> str:
    """One block per value, or per bucket (mean) when there are more values than `width`."""
    if not values:
        return ""
    if len(values) > width:
        edges = [round(i * len(values) / width) for i in range(width + 1)]
        values = [statistics.fmean(values[a:b]) for a, b in pairwise(edges)]
    low, high = min(values), max(values)
    scale = (len(SPARK) - 1) / (high - low) if high > low else 0.0
    return "".join(SPARK[round((v - low) * scale)] for v in values)


@dataclass
class WorkerRow:
    node: str
    role: str = "?"
    state: str = "idle"  # idle | working | delivering | gone
    job: str = ""
    agent: str = ""  # the child trained or the agent evaluated
    env_steps: int = 0
    total_steps: int = 0
    recent_return: float | None = None
    steps_per_s: float = 0.0
    heard: float = 0.0


class RunView(Handler):
    """What is known of a run, folded from its messages; `render` draws it."""

    def __init__(self, run: str) -> None:
        self.run = run
        self.status: RunStatus | None = None
        self.status_at = 0.0
        self.population = 0
        self.workers: dict[str, WorkerRow] = {}
        self.history = RunHistory()
        self.rejected = 0  # by this monitor

    @property
    def heard(self) -> bool:
        """Whether anything of the run came: a message (the fold took its run) or a node."""
        return self.history.run is not None or bool(self.workers)

    @property
    def births(self) -> list[Birth]:
        return self.history.births

    @property
    def settled(self) -> int:
        """Children heard born or given up."""
        return len(self.history.births) + len(self.history.failed)

    def _row(self, node: str, now: float) -> WorkerRow:
        row = self.workers.setdefault(node, WorkerRow(node))
        row.heard = now
        return row

    def apply(self, msg: MessageBase, now: float) -> None:
        if msg.run != self.run:
            return
        self.history.apply(msg)
        self.dispatch(msg, now)

    @handles(RunStatus)
    def _status(self, msg: RunStatus, now: float) -> None:
        self.status, self.status_at = msg, now

    @handles(PopulationSnapshot)
    def _population(self, msg: PopulationSnapshot, now: float) -> None:
        self.population = len(msg.members)

    @handles(WorkerReady)
    def _ready(self, msg: WorkerReady, now: float) -> None:
        row = self._row(msg.node, now)
        row.role, row.state, row.job = msg.role, "idle", ""

    @handles(TrainJob, EvalJob)
    def _job(self, msg: TrainJob | EvalJob, now: float) -> None:
        row = self._row(msg.node, now)
        row.role = "trainer" if isinstance(msg, TrainJob) else "evaluator"
        row.state, row.job, row.env_steps, row.total_steps = "working", msg.job, 0, msg.steps
        row.agent = msg.agent if isinstance(msg, TrainJob) else f"{msg.agent}/{msg.task}"
        row.recent_return = None

    @handles(TrainProgress)
    def _progress(self, msg: TrainProgress, now: float) -> None:
        row = self._row(msg.node, now)
        row.state, row.job, row.env_steps, row.total_steps = (
            "working",
            msg.job,
            msg.env_steps,
            msg.total_steps,
        )
        if not row.agent.startswith(msg.agent):  # keeps an evaluation's "agent/task"
            row.agent = msg.agent
        row.steps_per_s = msg.steps_per_s
        if msg.recent_return is not None:
            row.recent_return = msg.recent_return

    @handles(FitnessReport, EvalResult)
    def _result(self, msg: FitnessReport | EvalResult, now: float) -> None:
        self._row(msg.node, now).state = "delivering"

    @handles(Ack, Reject)
    def _answer(self, msg: Ack | Reject, now: float) -> None:
        self._row(msg.node, now).state = "idle"

    def liveliness(self, role: str, node: str, up: bool, now: float) -> None:
        row = self._row(node, now)
        row.role = role
        if not up:
            row.state = "gone"
        elif row.state == "gone":
            row.state = "idle"

    # --- drawing -----------------------------------------------------------------------------

    def best(self) -> tuple[float, str] | None:
        s = self.status
        if s is not None and s.best_fitness is not None and s.best_agent is not None:
            return s.best_fitness, s.best_agent
        if self.births:
            top = max(self.births, key=lambda b: b.fitness)
            return top.fitness, top.agent
        return None

    def render(self, now: float) -> Group:
        return Group(self._header(now), self._workers(now), self._births(), self._spark())

    def _header(self, now: float) -> Panel:
        s = self.status
        best = self.best()
        working = [w for w in self.workers.values() if w.state == "working"]
        speed = s.steps_per_s if s else sum(w.steps_per_s for w in working)
        fields = [
            f"born {s.born}/{s.target}" if s else f"born {len(self.births)} (no status yet)",
            f"best {best[0]:.2f} ({best[1]})" if best else "best -",
            f"{speed:,.0f} steps/s",
        ]
        if s:
            fields += [
                f"evaluated {s.evaluated}/{s.eval_target}",
                f"failed {s.failed}",
                f"repeats {s.repeats}",
                f"in flight {s.in_flight}",
                f"workers {s.workers_alive}",
                f"rejected {s.rejected}",
            ]
            if s.audited or s.quarantined:
                fields.append(f"audited {s.audited}")
            if s.quarantined:
                fields.append(f"QUARANTINED {', '.join(s.quarantined)} "
                              f"(retraining {s.retraining})")  # fmt: skip
        if self.population:
            fields.append(f"population {self.population}")
        if self.rejected:
            fields.append(f"monitor rejected {self.rejected}")
        if s:
            fields.append("DONE" if s.done else f"status {now - self.status_at:.1f} s ago")
        return Panel(Text("   ".join(fields)), title=f"derl run {self.run}", title_align="left")

    def _workers(self, now: float) -> Table:
        table = Table(title="workers", title_justify="left", expand=False)
        for column in ("node", "role", "state", "job", "body"):
            table.add_column(column)
        for column in ("env steps", "return", "steps/s", "heard"):
            table.add_column(column, justify="right")
        rows = sorted(self.workers.values(), key=lambda w: w.node)[:MAX_WORKER_ROWS]
        for w in rows:
            share = f" ({w.env_steps / w.total_steps:.0%})" if w.total_steps else ""
            table.add_row(
                w.node,
                w.role,
                w.state,
                w.job,
                w.agent,
                f"{w.env_steps:,}/{w.total_steps:,}{share}" if w.total_steps else "",
                "" if w.recent_return is None else f"{w.recent_return:.2f}",
                f"{w.steps_per_s:,.0f}",
                f"{now - w.heard:.1f} s",
                style="dim" if w.state == "gone" else None,
            )
        return table

    def _births(self) -> Table:
        table = Table(title="recent births", title_justify="left")
        table.add_column("#", justify="right")
        for column in ("agent", "parent", "mutation"):
            table.add_column(column)
        table.add_column("fitness", justify="right")
        table.add_column("node (or the body it repeats)")
        first = max(0, len(self.births) - RECENT_BIRTHS)
        for number, b in enumerate(self.births[first:], start=first + 1):
            trained = f"= {b.repeat_of}" if b.repeat_of else b.node
            table.add_row(
                str(number),
                b.agent,
                b.parent or "-",
                b.mutation or "-",
                f"{b.fitness:.2f}",
                trained,
            )
        return table

    def _spark(self) -> Text:
        values = [b.fitness for b in self.births]
        if not values:
            return Text("fitness over births: none yet")
        return Text(
            f"fitness over {len(values)} births: {sparkline(values)}  "
            f"(min {min(values):.2f}, max {max(values):.2f}, last {values[-1]:.2f})"
        )


def monitor(
    options: ZenohOptions, run: str | None, once: float | None, stop: threading.Event
) -> RunView:
    """Watch a run (`run`, or the only one on the bus) until `stop`; with `once`, look for the
    run for up to that many seconds (at least `DISCOVERY_S`), gather for that many seconds and
    print one plain snapshot."""
    console = Console() if sys.stdout.isatty() else Console(width=PIPED_WIDTH)
    inbox: deque[tuple[float, MessageBase | tuple[str, str, bool]]] = deque(maxlen=QUEUE)
    with open_session(options) as session:
        view = RunView(choose_run(session, run, max(once or 0.0, DISCOVERY_S)))
        checker = Checker(session)
        rejected = 0

        def on_sample(sample: zenoh.Sample, arrival: float) -> None:
            nonlocal rejected
            message = checker.check(str(sample.key_expr), sample.payload.to_bytes())
            if message is None:
                rejected += 1
            else:
                inbox.append((arrival, message))

        keys = KeySpace(view.run)
        tap = Tap(session, keys.everything(), on_sample)

        def ask_births() -> int:
            """Those before we came, and any that went by unheard (journaled just before a
            coordinator crash and never published): how many the coordinator answered with."""
            return ask(session, keys.all("births"), on_sample)

        ask_births()
        gap = 0  # what asking cannot fill (a late monitor of a run beyond the births remembered)
        Bus(session, view.run).watch_alive(
            lambda role, node, up: inbox.append((time.monotonic(), (role, node, up)))
        )

        def update() -> Group:
            nonlocal gap
            while inbox:
                at, item = inbox.popleft()
                if isinstance(item, MessageBase):
                    view.apply(item, at)
                else:
                    view.liveliness(*item, at)
            view.rejected = rejected
            if view.status is not None:
                missing = view.status.born + view.status.failed - view.settled
                if missing > gap:  # one went by unheard: its answer comes with the next update
                    # an answer short of all it remembers (a coordinator just restarted, its
                    # queryable not reached yet): asked again at the next update
                    gap = missing if ask_births() >= REMEMBERED_BIRTHS else 0
                else:
                    gap = missing
            return view.render(time.monotonic())

        if once is not None:
            end = time.monotonic() + once
            while not stop.wait(max(0.0, min(REFRESH_S, end - time.monotonic()))):
                if time.monotonic() >= end:
                    break
                update()  # folds what came, and asks for births that went by unheard
            console.print(update())
        else:
            quiet = logging.getLogger("derl")  # rejections are counted in the header instead
            level = quiet.level
            quiet.setLevel(logging.ERROR)
            try:
                with Live(update(), console=console, auto_refresh=False) as live:
                    while not stop.wait(REFRESH_S):
                        live.update(update(), refresh=True)
            finally:
                quiet.setLevel(level)
    tap.join()
    return view
