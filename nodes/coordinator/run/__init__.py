"""An evolution run's coordinator rules: `rules.EvolutionRules` (tournaments, repeats, reports,
births, failures), its state (`state.EvolutionState`), its audits (`audits`) and the files beside
its journal (`files`)."""
