"""A lying trainer for tests: derl's own trainer whose every fitness report says 1.25 x + 1 of the
fitness it trained, with its real checkpoint and everything else as trained (the issue's liar).
Run: python -m derl.nodes.testing.liar --run RUN --connect ENDPOINT --name NAME"""

from __future__ import annotations

import argparse
import signal

from derl.lifetime import LifetimeResult
from derl.messages import Curve, FitnessReport, TrainJob
from derl.nodes.cli.main import log_to_stderr
from derl.nodes.runtime.bus import ZenohOptions
from derl.nodes.worker.node import Worker


def lie(fitness: float) -> float:
    """What the liar says of `fitness`."""
    return 1.25 * fitness + 1.0


class LyingTrainer(Worker):
    """A trainer that inflates every fitness it reports (`lie`)."""

    def _fitness_report(
        self, job: TrainJob, summary: LifetimeResult, curve: Curve, checkpoint: bytes
    ) -> FitnessReport:
        report = super()._fitness_report(job, summary, curve, checkpoint)
        return report.model_copy(update={"fitness": lie(report.fitness)})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--connect", required=True)
    parser.add_argument("--name", required=True)
    args = parser.parse_args()
    log_to_stderr()  # as derl's own trainer logs
    worker = LyingTrainer(args.run, args.name, "trainer", 1)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: worker.stop.set())
    worker.serve(ZenohOptions(connect=(args.connect,)))


if __name__ == "__main__":
    main()
