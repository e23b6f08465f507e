"""Launch files: their model, the command line of every node process, the supervisor."""
