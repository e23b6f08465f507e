"""The coordinator node: one loop (`node`) over a ledger (`ledger`: journal, state, replies), with
its rules (`rules`) deciding what messages mean: a run's (`run`: rules, state, audits, files) or
a study's (`study`: rules, state, files)."""
