"""What `pip install derl` puts on a machine: one top-level import package, `derl`, whose science
part (`derl/` less `derl.messages` and `derl.nodes`) imports neither the wire nor the nodes."""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"derl": "derl", "derl.messages": "messages", "derl.nodes": "nodes"}


def _packages_on_disk() -> set[str]:
    found = set()
    for package, folder in FOLDERS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            relative = init.parent.relative_to(ROOT / folder)
            found.add(".".join((package, *relative.parts)))
    return found


def test_every_package_folder_is_installed_under_derl() -> None:
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert set(setuptools["packages"]) == _packages_on_disk()
    assert setuptools["package-dir"] == {k: v for k, v in FOLDERS.items() if k != v}


def test_the_wheel_holds_one_top_level_package(tmp_path: Path) -> None:
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", *FOLDERS.values()):
        copy = shutil.copytree if (ROOT / name).is_dir() else shutil.copy
        copy(ROOT / name, source / name)
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
         str(source), "-w", str(tmp_path / "dist")],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    (wheel,) = (tmp_path / "dist").glob("derl-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")} == {
        "derl"
    }
    assert "derl/messages/codec.py" in names
    assert "derl/nodes/cli/main.py" in names
    assert "derl/nodes/launch/local.yaml" in names  # the graph `derl run` starts


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def test_the_science_imports_neither_the_bus_nor_the_nodes() -> None:
    """Imports run one way: derl.nodes -> derl.messages -> the science."""
    forbidden = ("derl.messages", "derl.nodes", "zenoh", "mcap")
    for path in (ROOT / "derl").rglob("*.py"):
        for name in _imports(path):
            assert not name.startswith(forbidden), f"{path.relative_to(ROOT)} imports {name}"
    for path in (ROOT / "messages").rglob("*.py"):
        for name in _imports(path):
            assert not name.startswith(("derl.nodes", "zenoh", "mcap")), (
                f"{path.relative_to(ROOT)} imports {name}"
            )


def test_the_messages_load_neither_mujoco_nor_torch() -> None:
    """A monitor that decodes messages needs pydantic and msgpack, not the simulator: loading
    `derl.messages` (whose messages carry a genome and PPO settings) imports neither."""
    loaded = subprocess.run(
        [sys.executable, "-c", "import sys, derl.messages; "
         "print(sorted({'mujoco', 'torch'} & set(sys.modules)))"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    assert loaded.strip() == "[]"


def test_a_coordinator_checks_a_reported_policy_without_torch() -> None:
    """The coordinator's check of a reported checkpoint (`policy_problem`, at every report) reads
    it without torch, whose import costs each coordinator about a second of CPU: the shipped FT
    agent passes, its bytes cut short do not, and torch is never loaded."""
    checked = subprocess.run(
        [sys.executable, "-c", "import sys; from pathlib import Path; "
         "import derl.nodes.coordinator.node, derl.nodes.coordinator.run.rules; "
         "from derl.policy_check import policy_problem; from derl.unimal import Genome; "
         "agent = Path('agents/ft'); data = (agent / 'checkpoint.pt').read_bytes(); "
         "genome = Genome.model_validate_json((agent / 'genome.json').read_text()); "
         "print(repr(policy_problem(data, genome, 'ft')), "
         "repr(policy_problem(data[:-100], genome, 'ft')), 'torch' in sys.modules)"],
        capture_output=True, text=True, check=True, cwd=ROOT,
    ).stdout  # fmt: skip
    assert checked.strip() == "'' 'the checkpoint does not load (BadZipFile)' False"


def test_the_mutation_operators_are_named_once_for_the_wire() -> None:
    from derl.unimal.mutations import OPERATORS
    from derl.unimal.space import OPERATOR_NAMES

    assert tuple(OPERATORS) == OPERATOR_NAMES
