"""Processes as /proc shows them: the ones a process started, the ones whose command line holds
given arguments, and a process's resident memory, open files and threads."""

from __future__ import annotations

import os
from pathlib import Path


def descendants(pid: int) -> list[int]:
    """The processes started by `pid`, and by them, now."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def with_arguments(*words: str) -> list[int]:
    """The processes on this machine whose command line holds `words` as consecutive arguments
    (e.g. "--name", "a")."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                argv = (entry / "cmdline").read_bytes().decode(errors="replace").split("\0")
            except OSError:
                continue
            if any(argv[k : k + len(words)] == list(words) for k in range(len(argv))):
                found.append(int(entry.name))
    return found


def sample(pid: int) -> dict[str, float] | None:
    """Resident memory (MB), open files and threads of `pid` now (None: it is gone)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    if "VmRSS" not in fields:  # a zombie
        return None
    return {
        "rss_mb": int(fields["VmRSS"].split()[0]) / 1024,
        "open_files": fds,
        "threads": int(fields["Threads"]),
    }
