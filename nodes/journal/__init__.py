"""The run's journal: MCAP segments (the format) and the one fold of them every reader uses."""
