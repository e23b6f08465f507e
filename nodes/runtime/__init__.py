"""What every node process uses: the Zenoh bus, checkpoint files, child processes."""
