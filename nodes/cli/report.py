"""`derl report`: the paper's analyses of finished (or running) runs, or of a study.

It reads runs through the journal's fold (`nodes.journal.history.run_log`: bodies in birth
order with their parent, body, mutation, fitness, curve, energy, cost of work and mass; the
evaluations) and hand those to `derl.analysis`.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console

from derl.nodes.cli.options import fail, output_directory
from derl.nodes.journal.history import load_runs

if TYPE_CHECKING:
    from derl.analysis import RunLog

console = Console()


def register(commands: argparse._SubParsersAction) -> None:
    report = commands.add_parser(
        "report",
        help="plots and tables of the paper's analyses of runs or of a study",
        description="Write DIR/index.html, one PNG per figure (figs. 2-6 of the paper and the "
        "best bodies), a GIF of each of the best bodies' gaits (from a run directory's "
        "checkpoints), CSV tables (bodies, lineages, series, world_series, muller, tests, "
        "test_summary; the tests with their budget in env steps) and stats.json, from the "
        "journals alone. Runs of one world are pooled as the paper pools them; a study "
        "(`derl study`) adds its retrainings (the top agents are then each world's best by "
        "mean retrained fitness) and its test results at every budget (figs. 4b and 4c).",
    )
    report.add_argument(
        "runs",
        nargs="+",
        type=Path,
        metavar="RUN_DIR_OR_LOG",
        help="run directory or MCAP log, or one study directory (`derl study`)",
    )
    report.add_argument("--out", type=Path, required=True, help="output directory")
    report.add_argument(
        "--beneficial",
        type=_thresholds,
        default={},
        metavar="GAIN|WORLD=GAIN,...",
        help="least fitness gain of a beneficial mutation: one number for every world, or per "
        "world, e.g. ft=300,vt=100 (default: the paper's ft=300, vt=100, mvt=100)",
    )
    report.add_argument(
        "--top", type=int, help="top agents (default 100, or a quarter of a smaller group)"
    )
    report.add_argument(
        "--stability-sample",
        type=int,
        metavar="N",
        help="bodies whose passive stability is simulated: all of a run up to N, else N evenly "
        "spaced in birth order (default 500)",
    )
    report.add_argument(
        "--processes",
        type=int,
        default=min(4, os.cpu_count() or 1),
        help="processes for the stability simulations (default: up to 4 cores)",
    )
    report.add_argument("--pictures", type=int, help="best bodies drawn (default 8)")
    report.add_argument(
        "--gaits",
        type=int,
        metavar="N",
        help="best bodies filmed walking, a short GIF each (default 3; 0: none)",
    )
    report.set_defaults(handler=_report)


def _thresholds(text: str) -> dict[str, float]:
    """``300`` (every world) or ``ft=300,vt=100``, as {world: gain}; "*" stands for every world."""
    try:
        if "=" not in text:
            return {"*": float(text)}
        pairs = (item.split("=", 1) for item in text.split(",") if item.strip())
        return {world.strip().lower(): float(gain) for world, gain in pairs}
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give a number or WORLD=GAIN pairs, e.g. ft=300,vt=100"
        ) from None


def _runs_or_study(paths: list[Path]) -> list[RunLog]:
    """The runs of `paths`, or a study's runs with its results (`derl study`)."""
    from derl.nodes.coordinator.study.files import SETUP_FILE, study_logs

    studies = [path for path in paths if (path / SETUP_FILE).is_file()]
    if not studies:
        return load_runs(paths)
    if len(paths) > 1:
        fail(f"{studies[0]} is a study: report it alone (it names its runs)")
    return study_logs(studies[0])


def _report(args: argparse.Namespace) -> int:
    from derl.analysis import AnalysisConfig, write_report
    from derl.analysis.config import BENEFICIAL

    everywhere = args.beneficial.pop("*", None)
    defaults = {w: everywhere for w in BENEFICIAL} if everywhere is not None else BENEFICIAL
    given = {
        "top": args.top,
        "stability_sample": args.stability_sample,
        "processes": args.processes,
        "pictures": args.pictures,
        "gaits": args.gaits,
    }
    try:
        config = AnalysisConfig(
            beneficial={**defaults, **args.beneficial},
            **{name: value for name, value in given.items() if value is not None},
        )
    except ValueError as error:
        fail(str(error))
    output_directory(args.out)  # before the runs are read
    start = time.monotonic()
    runs = _runs_or_study(args.runs)
    try:
        files = write_report(runs, args.out, config)
    except ValueError as error:
        fail(str(error))
    for note in files.notes:
        console.print(f"note: {note}", highlight=False)
    for line in files.headline:
        console.print(line, highlight=False)
    for run in runs:
        if run.fingerprint is not None:
            audits = f", {run.audited} audited" if run.audited else ""
            console.print(f"{run.name}: fingerprint {run.fingerprint} ({len(run.bodies)} "
                          f"births{audits})", highlight=False)  # fmt: skip
    console.print(
        f"wrote {files.page} ({len(files.figures)} figures, {len(files.gaits)} gaits, "
        f"{len(files.tables)} tables) in "
        f"{time.monotonic() - start:.1f} s",
        highlight=False,
    )
    return 0
