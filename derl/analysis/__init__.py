"""The paper's analyses of evolution runs, from plain records (never messages or files):
lineages, Muller abundances, morphology over time, the Baldwin effect, energy efficiency, the
test-task suite, and the appendix D selection of bodies to retrain; plotted and tabulated by
`write_report`, which also films the best bodies from their checkpoints."""

from derl.lazy import exports

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
