"""What a coordinator's messages mean: the interface between the node loop and its rules.

The loop (`node.Coordinator`) is the same for every coordinator: it takes the bus's messages in
groups, commits through its `Ledger` (journal, state, replies released once on disk), keeps the
workers' liveliness and the jobs' leases, answers queries and publishes the status. What a message
means is its rules': which job a ready worker gets, whether a result is taken (a birth, an
evaluation) or rejected, what a failed job leads to, what the run looks like and what it leaves
in its directory. Two rule sets exist: `EvolutionRules` (a run: `run/rules.py`) and `StudyRules`
(the paper's appendix D: `study/rules.py`). Rules change the state only by committing messages
through the ledger it is given at `start`, so a restarted coordinator rebuilds it from the journal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from derl.messages import (
    EvalJob,
    EvalResult,
    FitnessReport,
    JobFailed,
    PopulationSnapshot,
    TrainJob,
)
from derl.nodes.coordinator.jobs import Job, JobBook
from derl.nodes.coordinator.ledger import Ledger


@dataclass(frozen=True)
class Progress:
    """The rules' part of `RunStatus`: children born of the target, the best so far, births
    checked by an audit and children to train again (`audits`)."""

    born: int = 0
    target: int = 0
    best_fitness: float | None = None
    best_agent: str | None = None
    audited: int = 0
    retraining: int = 0


class Rules(Protocol):
    """What the node loop asks of a coordinator's rules ("policy" in derl is the trained
    controller only: `derl.rl.Policy`)."""

    @property
    def state(self) -> JobBook:
        """The journal's fold: the loop applies every committed message to it (and on a restart
        every journaled one) and reads from it the jobs in flight, the results and whether it is
        over."""

    def start(self, ledger: Ledger) -> None:
        """The journal is replayed into `state` and open: commit through `ledger` from now on, and
        redo what a restart may have left undone."""

    def next_job(self, node: str, role: str, trainers: int) -> TrainJob | EvalJob | None:
        """The job for `node` (a `role` worker that is ready; `trainers` are alive), committing
        what is decided on the way (tournaments, repeats born), or None if there is none now.
        The loop commits the job."""

    def on_fitness(self, report: FitnessReport) -> None:
        """Take a fitness report (a birth, acknowledged) or reject it."""

    def on_evaluation(self, result: EvalResult) -> None:
        """Take an evaluation's result (acknowledged) or reject it."""

    def on_failure(self, failure: JobFailed, job: Job) -> None:
        """`job` failed (`failure`, committed: the job is taken back): what follows, such as
        giving its child up after too many failures."""

    def progress(self) -> Progress:
        """Births and the best so far, for the status."""

    def snapshot(self) -> PopulationSnapshot:
        """The population now (for the periodic snapshot and the `population` query)."""

    def log_progress(self) -> None:
        """Log one line for what happened since the last call (called once a second)."""

    def finish(self) -> None:
        """The run is over: write its results into its directory."""
