"""Reference bodies for the benchmarks: a 6-limb and a 10-limb UNIMAL, the same on every run and
every version (`reference_bodies.json`: drawn once, on 2026-12-03, so that figures measured before
and after a change of the mutations compare the same bodies)."""

from __future__ import annotations

import json
from pathlib import Path

from derl.unimal import Genome

FILE = Path(__file__).with_name("reference_bodies.json")


def reference_body(limbs: int) -> Genome:
    """The reference body with `limbs` limbs (6 or 10)."""
    return Genome.model_validate(json.loads(FILE.read_text())[str(limbs)])
