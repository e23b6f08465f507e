"""The paper's analyses of evolution runs, from plain records (never messages or files):
lineages, Muller abundances, morphology over time, the Baldwin effect, energy efficiency, the
test-task suite, and the appendix D selection of bodies to retrain; plotted and tabulated by
`write_report`, which also films the best bodies from their checkpoints."""

from derl.analysis.compute import Analysis, RunAnalysis, analyse
from derl.analysis.config import AnalysisConfig
from derl.analysis.records import Body, Evaluation, Retraining, RunLog
from derl.analysis.report import ReportFiles, write_report
from derl.analysis.selection import RetrainJob, RetrainPlan, by_mean_fitness, plan
from derl.analysis.statistics import BootstrapConfig

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
