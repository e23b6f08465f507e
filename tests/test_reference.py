"""The generated references are current, `derl schema` prints schemas, misspelt keys are named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from derl.messages import MESSAGE_TYPES, SCHEMA_VERSION, Birth
from derl.nodes.cli.main import main
from derl.nodes.tools.reference import DOCUMENTS, command

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", list(DOCUMENTS))
def test_committed_document_is_what_the_code_writes(name: str) -> None:
    committed = (ROOT / "docs" / f"{name}.md").read_text()
    assert committed == DOCUMENTS[name](), f"docs/{name}.md is out of date: run `{command(name)}`"


def test_protocol_names_every_message_and_key() -> None:
    text = DOCUMENTS["protocol"]()
    assert f"Schema version: **{SCHEMA_VERSION}**" in text
    for name in MESSAGE_TYPES:
        assert f"### {name}\n" in text
    fitness = "| `derl/<run>/fitness/<node>/<agent>` | [FitnessReport](#fitnessreport) | trainer |"
    assert fitness in text
    assert "| `derl/<run>/status` | [RunStatus](#runstatus) | coordinator | DROP |" in text


def _derl(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    try:
        code = main(list(argv))
    except SystemExit as stop:
        code = stop.code
    out, err = capsys.readouterr()
    return code, out, err


def test_schema_prints_a_types_json_schema(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _derl(capsys, "schema", "Birth")
    schema = json.loads(out)
    assert code == 0 and schema == Birth.model_json_schema()
    assert schema["type"] == "object" and set(schema["properties"]) == set(Birth.model_fields)
    assert schema["properties"]["birth"]["description"]


def test_schema_lists_the_types(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _derl(capsys, "schema")
    lines = out.splitlines()
    assert code == 0 and lines[0] == f"schema version {SCHEMA_VERSION}"
    assert [line.split()[0] for line in lines[1:]] == list(MESSAGE_TYPES)


def test_unknown_type_is_one_line_and_exit_status_2(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _derl(capsys, "schema", "Brith")
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and "'Brith'" in err and "Birth, ChildFailed" in err


def test_markdown_prints_a_document(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _derl(capsys, "schema", "--markdown", "configuration")
    assert code == 0 and out == DOCUMENTS["configuration"]()


def test_misspelt_launch_file_key_names_the_valid_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = yaml.safe_load((ROOT / "launch" / "local.yaml").read_text())
    data["hosts"][0]["nodes"][0]["cont"] = 2
    path = tmp_path / "typo.yaml"
    path.write_text(yaml.safe_dump(data))
    code, _, err = _derl(capsys, "launch", str(path), "--dry-run")
    assert code == 1 and err.count("\n") == 1
    assert "unknown key 'hosts.0.nodes.0.cont'; valid keys: role, count, threads," in err


def test_misspelt_profile_key_names_the_valid_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "typo.yaml"
    path.write_text("profile: smoke\npopulaton: 4\n")
    code, _, err = _derl(capsys, "run", "--profile", str(path), "--run-dir", str(tmp_path / "r"))
    assert code == 1 and "unknown key 'populaton'; valid keys: name, world, population," in err
    assert err.rstrip().endswith(", profile")
