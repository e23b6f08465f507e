"""A study's coordinator rules (appendix D): `rules.StudyRules`, its state (`state.StudyState`)
and the files beside its journal (`files`)."""
