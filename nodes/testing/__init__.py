"""What the tests and the bench/ scripts share to drive and check runs: simulated trainers, the
crash checker, the soak, process helpers, waiting on a condition. No node imports it."""
