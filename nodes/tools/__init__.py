"""Tools that watch, record, replay and inspect runs: topic, monitor, record/replay, logs."""
