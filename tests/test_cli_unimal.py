"""`derl unimal ...` run as a user would: real processes, real files, real offscreen rendering."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import matplotlib.image
import mujoco

from derl.unimal import Genome, check_body
from derl.unimal.count import count_design_space


def derl(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "derl.nodes.cli", *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=check,
    )


def test_sample_show_render(tmp_path: Path) -> None:
    derl("unimal", "sample", "--n", "4", "--seed", "7", "--out", str(tmp_path))
    genomes = sorted(tmp_path.glob("*.json"))
    assert len(genomes) == 4
    for path in genomes:
        genome = Genome.model_validate_json(path.read_text())
        check_body(genome)
        model = mujoco.MjModel.from_xml_path(str(path.with_suffix(".xml")))
        assert model.nu == genome.dof
    shown = json.loads(derl("unimal", "show", str(genomes[0]), "--json").stdout)
    assert shown["num_limbs"] == Genome.model_validate_json(genomes[0].read_text()).num_limbs
    derl("unimal", "render", str(genomes[0]), "--out", str(tmp_path / "one.png"))
    derl(
        "unimal", "render", str(tmp_path), "--out", str(tmp_path / "grid.png"), "--size", "80", "60"
    )
    one = matplotlib.image.imread(tmp_path / "one.png")
    grid = matplotlib.image.imread(tmp_path / "grid.png")
    assert one.shape[:2] == (240, 320)
    assert grid.shape[:2] == (2 * 60 + 4, 2 * 80 + 4)
    assert one.std() > 0.05  # a picture, not a blank


def test_bad_genome_gives_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"head_density": 500, "limb_density": 500, "limbs": [{"id": 0}]}))
    result = derl("unimal", "show", str(bad), check=False)
    assert result.returncode != 0
    assert "is not a valid genome" in result.stderr and "length" in result.stderr


def test_count() -> None:
    summary = json.loads(derl("unimal", "count").stdout)
    assert summary["bodies_with_1_to_max_limbs"] == f"{count_design_space().total:.3e}"
