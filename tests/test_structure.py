"""The code's shape, checked: nothing below the command line exits the process (it raises a
`derl.nodes.errors.DerlError`, which `derl.nodes.cli.main` alone turns into a line and an exit
status)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("derl", "messages", "nodes")
CLI = ROOT / "nodes" / "cli"


def _sources() -> list[Path]:
    return sorted(path for folder in FOLDERS for path in (ROOT / folder).rglob("*.py"))


def test_nothing_below_the_command_line_exits_the_process() -> None:
    exits = []
    for path in _sources():
        if path.is_relative_to(CLI):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            called = node.exc if isinstance(node, ast.Raise) else node
            if isinstance(called, ast.Call):
                called = called.func
            name = getattr(called, "id", getattr(called, "attr", None))
            if isinstance(node, ast.Raise | ast.Call) and name in ("SystemExit", "exit", "_exit"):
                exits.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not exits, f"exits below the command line: {exits}"
