"""The paper's analyses of evolution runs, from plain records (never messages or files):
lineages, Muller abundances, morphology over time, the Baldwin effect, energy efficiency, the
test-task suite, and the appendix D selection of bodies to retrain; plotted and tabulated by
`write_report`, which also films the best bodies from their checkpoints."""

from typing import TYPE_CHECKING

from derl.lazy import exports

if TYPE_CHECKING:  # imported on first use: scipy and matplotlib only when analysing
    from derl.analysis.compute import Analysis, RunAnalysis, analyse
    from derl.analysis.config import AnalysisConfig
    from derl.analysis.records import Body, Evaluation, Retraining, RunLog
    from derl.analysis.report import ReportFiles, write_report
    from derl.analysis.selection import RetrainJob, RetrainPlan, by_mean_fitness, plan
    from derl.analysis.statistics import BootstrapConfig

_HOMES = {
    "Analysis": "compute",
    "AnalysisConfig": "config",
    "Body": "records",
    "BootstrapConfig": "statistics",
    "Evaluation": "records",
    "ReportFiles": "report",
    "RetrainJob": "selection",
    "RetrainPlan": "selection",
    "Retraining": "records",
    "RunAnalysis": "compute",
    "RunLog": "records",
    "analyse": "compute",
    "by_mean_fitness": "selection",
    "plan": "selection",
    "write_report": "report",
}
__all__ = [
    "Analysis",
    "AnalysisConfig",
    "Body",
    "BootstrapConfig",
    "Evaluation",
    "ReportFiles",
    "RetrainJob",
    "RetrainPlan",
    "Retraining",
    "RunAnalysis",
    "RunLog",
    "analyse",
    "by_mean_fitness",
    "plan",
    "write_report",
]
__getattr__ = exports(__name__, _HOMES)
