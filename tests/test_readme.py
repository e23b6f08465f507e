"""The README runs as written: every `derl` command in its code blocks is one the command line
takes (parsed, not run), and its cheap blocks run: the Python snippets and the body commands."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from nodes_fixtures import REPO

from derl.nodes.cli.main import build_parser, main

README = REPO / "README.md"
CHEAP = ("derl unimal",)
"""Shell lines of the README that a test runs (the rest trains or evolves for minutes)."""


def _blocks(language: str) -> list[str]:
    """The README's fenced code blocks of `language` ("" for those without one)."""
    blocks: list[str] = []
    inside: str | None = None  # the open block's language
    for line in README.read_text().splitlines():
        if line.startswith("```"):
            if inside is None:
                inside = line[3:].strip()
                if inside == language:
                    blocks.append("")
            else:
                inside = None
        elif inside == language:
            blocks[-1] += line + "\n"
    return blocks


def _derl_lines() -> list[str]:
    """Each `derl ...` command of the README's shell blocks, without comments and pipes."""
    lines = []
    for block in _blocks(""):
        for line in block.splitlines():
            command = line.split("#", 1)[0].split("|", 1)[0].strip()
            if command.startswith("derl "):
                lines.append(command)
    return lines


def test_every_derl_command_in_the_readme_parses() -> None:
    lines = _derl_lines()
    assert len(lines) > 20
    parser = build_parser()
    for line in lines:
        try:
            parser.parse_args(shlex.split(line)[1:])
        except SystemExit:
            pytest.fail(f"the README's `{line}` is not a derl command line")


@pytest.mark.slow
def test_the_readme_python_and_body_commands_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    env = {**os.environ, "MUJOCO_GL": "egl", "SB3_LOGDIR": str(tmp_path)}  # SB3's logger's folder
    snippets = _blocks("python")
    assert len(snippets) == 3
    for snippet in snippets:  # from the repository (agents/ft), as a reader's checkout
        done = subprocess.run([sys.executable, "-c", snippet], cwd=REPO, env=env,
                              capture_output=True, text=True, timeout=300)  # fmt: skip
        assert done.returncode == 0, f"{snippet}\n{done.stderr}"
    monkeypatch.chdir(tmp_path)  # the body commands as `derl` runs them, in this process
    for line in [line for line in _derl_lines() if line.startswith(CHEAP)]:
        assert main(shlex.split(line)[1:]) == 0, line
    assert (tmp_path / "population.png").is_file()
