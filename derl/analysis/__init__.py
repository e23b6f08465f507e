"""The paper's analyses of evolution runs, from plain records (never messages or files):
lineages, Muller abundances, morphology over time, the Baldwin effect, energy efficiency, the
test-task suite, and the appendix D selection of bodies to retrain; plotted and tabulated by
`write_report`, which also films the best bodies from their checkpoints."""

from typing import TYPE_CHECKING

from derl.lazy import exports

if TYPE_CHECKING:  # the names for type checkers, which do not run `__getattr__`
    from derl.analysis.compute import Analysis as Analysis
    from derl.analysis.compute import RunAnalysis as RunAnalysis
    from derl.analysis.compute import analyse as analyse
    from derl.analysis.config import AnalysisConfig as AnalysisConfig
    from derl.analysis.records import Body as Body
    from derl.analysis.records import Evaluation as Evaluation
    from derl.analysis.records import Retraining as Retraining
    from derl.analysis.records import RunLog as RunLog
    from derl.analysis.report import ReportFiles as ReportFiles
    from derl.analysis.report import write_report as write_report
    from derl.analysis.selection import RetrainJob as RetrainJob
    from derl.analysis.selection import RetrainPlan as RetrainPlan
    from derl.analysis.selection import kept_bodies as kept_bodies
    from derl.analysis.selection import plan as plan
    from derl.analysis.selection import rank_by_mean as rank_by_mean
    from derl.analysis.statistics import BootstrapConfig as BootstrapConfig

# imported on first use: scipy and matplotlib only when analysing
__getattr__, __all__ = exports(
    __name__,
    {
        "compute": ("Analysis", "RunAnalysis", "analyse"),
        "config": ("AnalysisConfig",),
        "records": ("Body", "Evaluation", "Retraining", "RunLog"),
        "report": ("ReportFiles", "write_report"),
        "selection": ("RetrainJob", "RetrainPlan", "kept_bodies", "plan", "rank_by_mean"),
        "statistics": ("BootstrapConfig",),
    },
)
