"""The code's shape, checked: nothing below the command line exits the process (it raises a
`derl.nodes.errors.DerlError`, which `derl.nodes.cli.main` alone turns into a line and an exit
status), and no production code relies on the example messages."""

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


def _imports(path: Path) -> set[str]:
    """The modules `path` imports, at module level or in a function (`from X import y`: X)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def test_only_the_protocol_reference_uses_the_example_messages() -> None:
    """`derl.messages.examples` are fixtures for tests and benchmarks, and the example payloads
    of docs/protocol.md (`nodes/tools/reference.py`); no other code relies on them."""
    users = {
        str(path.relative_to(ROOT))
        for path in _sources()
        if "derl.messages.examples" in _imports(path)
    }
    assert users == {"nodes/tools/reference.py"}
