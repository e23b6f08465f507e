"""The coordinator node: its state (a fold over the journal) and its loop."""
