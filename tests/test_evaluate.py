"""`derl evaluate`: the retraining jobs of a `derl select` plan, run on this host."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

from derl.analysis import RetrainJob, RetrainPlan
from derl.unimal import Genome


def test_evaluate_runs_a_plan(quadruped: Genome, tmp_path: Path) -> None:
    jobs = tuple(
        RetrainJob(
            run="r",
            agent="a1",
            lineage="i0000",
            fitness=10.0,
            task="ft",
            steps=None,
            seed=seed,
            genome=quadruped,
        )
        for seed in (11, 12)
    )
    plan = tmp_path / "plan.json"
    plan.write_text(RetrainPlan(per_lineage=1, seeds=(11, 12), jobs=jobs).model_dump_json())
    out = tmp_path / "out"
    command = [sys.executable, "-m", "nodes.cli", "evaluate", str(plan), "--out", str(out)]
    missing = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert missing.returncode != 0 and "no step budget" in missing.stderr
    subprocess.run([*command, "--steps", "4096"], check=True, capture_output=True, timeout=300)
    rows = list(csv.DictReader((out / "retrained.csv").open()))
    assert sorted(int(r["seed"]) for r in rows) == [11, 12]
    best = json.loads((out / "best.json").read_text())
    assert len(best) == 1 and best[0]["agent"] == "a1" and best[0]["seeds"] == 2
