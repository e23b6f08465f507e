"""The coordinator node: one loop (`node`) over a ledger (`ledger`: journal, state, replies), with
a policy (`policy`) deciding what messages mean: a run's (`evolution`) or a study's (`study`)."""
