"""derl's modules and what each is for, read from the source files (docs/modules.md): every
package folder and module with the first sentence of its docstring, in the repository's layout.
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from importlib.util import find_spec
from pathlib import Path
from typing import Final

FOLDERS: Final = {"derl": "derl", "derl.messages": "messages", "derl.nodes": "nodes"}
"""Each installed package whose source is a folder of its own in the repository: that folder."""

_SENTENCE_END = re.compile(r"\.(?=\s+[A-Z]|\s*$)")


@dataclass(frozen=True)
class Entry:
    path: str
    """In the repository: a package's folder (``nodes/coordinator/``) or a module's file."""
    job: str
    """The first sentence of its docstring ("" without one)."""


def module_tree() -> list[Entry]:
    """Every package folder (then its modules, then its subpackages) of each of `FOLDERS`."""
    entries = []
    for package, folder in FOLDERS.items():
        spec = find_spec(package)
        assert spec is not None and spec.origin is not None, package
        entries += _folder(Path(spec.origin).parent, folder, package)
    return entries


def _folder(directory: Path, shown: str, package: str) -> list[Entry]:
    entries = [Entry(f"{shown}/", _job(directory / "__init__.py"))]
    for path in sorted(directory.glob("*.py")):
        if path.name != "__init__.py":
            entries.append(Entry(f"{shown}/{path.name}", _job(path)))
    for sub in sorted(d for d in directory.iterdir() if (d / "__init__.py").is_file()):
        if f"{package}.{sub.name}" not in FOLDERS:  # a folder of its own (an installed wheel)
            entries += _folder(sub, f"{shown}/{sub.name}", f"{package}.{sub.name}")
    return entries


def _job(path: Path) -> str:
    """The first sentence of `path`'s docstring, in one line."""
    paragraph = (ast.get_docstring(ast.parse(path.read_text())) or "").split("\n\n")[0]
    text = " ".join(paragraph.replace("``", "`").split())
    end = _SENTENCE_END.search(text)
    return text[: end.end()] if end else text
