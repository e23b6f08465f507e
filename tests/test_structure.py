"""The code's shape, checked: no import cycle among derl's modules (module-level, inside a
function, or for type checking only), nothing below the command line exits the process (it raises a
`derl.nodes.errors.DerlError`, which `derl.nodes.cli.main` alone turns into a line and an exit
status), no production code relies on the example messages, and the documents describe the
folders and files that exist."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from derl.nodes.tools.module_tree import module_tree

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"derl": "derl", "derl.messages": "messages", "derl.nodes": "nodes"}  # name: folder
CLI = ROOT / "nodes" / "cli"


def _sources() -> list[Path]:
    return sorted(path for folder in PACKAGES.values() for path in (ROOT / folder).rglob("*.py"))


def _modules() -> dict[str, Path]:
    """Every module of derl by its import name (a package by its `__init__.py`)."""
    found = {}
    for package, folder in PACKAGES.items():
        for path in (ROOT / folder).rglob("*.py"):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join((package, *parts))] = path
    return found


def _imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The modules of derl that module `name` imports (at module level, in a function, or in an
    `if TYPE_CHECKING:` block: a module that needs another's types depends on it as much;
    `from A import b` imports A.b where it is a module, else A)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    stack: list[ast.AST] = [ast.parse(path.read_text())]
    while stack:
        node = stack.pop()
        for child in ast.iter_child_nodes(node):
            stack.append(child)
            if isinstance(child, ast.Import):
                found.update(alias.name for alias in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:  # relative: from the package, up `level - 1` packages
                    up = package.rsplit(".", child.level - 1)[0] if child.level > 1 else package
                    base = f"{up}.{base}" if base else up
                for alias in child.names:
                    found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
    return {module for module in found if module in modules and module != name}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for other in graph[module]:
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            component = []
            while not component or component[-1] != module:
                component.append(stack.pop())
            if len(component) > 1:
                cycles.append(sorted(component))

    for module in graph:
        if module not in index:
            visit(module)
    return cycles


def test_no_import_cycle_among_derls_modules() -> None:
    modules = _modules()
    graph = {name: _imports_of(name, path, modules) for name, path in modules.items()}
    assert graph["derl.nodes.coordinator.node"] >= {"derl.nodes.coordinator.ledger"}  # it reads
    assert "derl.analysis" in graph["derl.nodes.coordinator.study.files"]  # inside a function
    assert _cycles(graph) == []


def test_the_cycle_check_finds_a_cycle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]


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


def test_only_the_protocol_reference_and_the_test_machinery_use_the_example_messages() -> None:
    """`derl.messages.examples` are fixtures for tests and benchmarks (the garbage
    `derl.nodes.testing.faults` puts on a bus), and the example payloads of docs/protocol.md
    (`nodes/tools/reference.py`); no other code relies on them."""
    modules = _modules()
    users = {
        str(path.relative_to(ROOT))
        for name, path in modules.items()
        if "derl.messages.examples" in _imports_of(name, path, modules)
    }
    assert users == {"nodes/tools/reference.py", "nodes/testing/faults.py"}


def _tree(document: str, section: str) -> set[str]:
    """The folders named by the first code block after the heading `section`: a line indented
    two spaces per level, starting with a folder (or several, comma-separated)."""
    block = document.split(f"\n{section}\n", 1)[1].split("```\n", 2)[1]
    folders: set[str] = set()
    parents: list[str] = []
    for line in block.splitlines():
        indent = len(line) - len(line.lstrip())
        names = [name.strip() for name in line.strip().split("  ")[0].split(",")]
        if indent % 2 or indent > 8 or not all(re.fullmatch(r"[\w.]+/", n) for n in names):
            continue  # a description's next line
        del parents[indent // 2 :]
        folders.update("".join([*parents, name]) for name in names)
        parents.append(names[0])
    return folders


def test_the_architecture_names_every_package_folder_and_only_those() -> None:
    named = _tree((ROOT / "docs" / "architecture.md").read_text(), "## Packages")
    packages = {entry.path for entry in module_tree() if entry.path.endswith("/")}
    assert {f for f in named if f.split("/")[0] in PACKAGES.values()} == packages
    assert [f for f in named if not (ROOT / f).is_dir()] == []


def test_the_docs_name_only_files_that_exist() -> None:
    """Every file of the repository a document (the README or a page of docs/) names exists
    (docs/fidelity.md names the released code's files too: not checked)."""
    path = re.compile(r"\b(?:derl|messages|nodes|launch|bench|tests|examples|docs)/[\w./-]*"
                      r"\.(?:py|yaml|md|json5?|sbatch|toml)\b")  # fmt: skip
    missing = [
        f"{document.name}: {name}"
        for document in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
        if document.name != "fidelity.md"
        for name in sorted(set(path.findall(document.read_text())))
        if not (ROOT / name).exists()
    ]
    assert missing == []


def _citable(document: Path) -> tuple[list[str], set[str]]:
    """What a section of `document` is cited by: its headings' and its tables' rows' first words
    (a row names a point: docs/fidelity.md's), and its headings' anchors (GitHub's)."""
    lines = document.read_text().splitlines()
    headings = [line.lstrip("#").strip() for line in lines if line.startswith("#")]
    rows = [line[1:].split("|")[0].strip() for line in lines if line.startswith("| ")]
    anchors = {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in headings}
    return headings + rows, anchors


def test_every_section_cited_exists() -> None:
    """Every section a document, a launch file or a module cites exists: `README "Heading"` or
    `docs/x.md, "Heading"` (the beginning of a heading or of a table's row) and `x.md#anchor`."""
    cited = re.compile(r"(README|[\w/-]+\.md)\)?,? \"([^\"]+)\"")
    linked = re.compile(r"\]\(([\w/.-]*\.md)?#([\w-]+)\)")
    citing = [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), ROOT / "agents" / "README.md",
              *(p for p in (ROOT / "launch").rglob("*") if p.is_file()),
              *(p for f in ("derl", "messages", "nodes", "bench", "examples")
                for p in (ROOT / f).rglob("*.py"))]  # fmt: skip
    missing = []
    for path in citing:
        text = re.sub(r"\s*\n\s*(?:#\s*)?", " ", path.read_text())  # a citation across lines
        for name, section in cited.findall(text):
            document = ROOT / ("README.md" if name == "README" else name)
            if not document.exists():
                document = path.parent / name
            if not any(s.startswith(section) for s in _citable(document)[0]):
                missing.append(f"{path.relative_to(ROOT)}: {name} {section!r}")
        for name, anchor in linked.findall(text):
            document = path.parent / name if name else path
            if anchor not in _citable(document)[1]:
                missing.append(f"{path.relative_to(ROOT)}: {name}#{anchor}")
    assert missing == []


def test_every_module_says_what_it_is_for() -> None:
    assert [entry.path for entry in module_tree() if not entry.job] == []
