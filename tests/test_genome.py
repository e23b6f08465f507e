"""The genome model: JSON round trip, and clear rejections before any MuJoCo call."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from derl.unimal import Genome


def test_json_round_trip_is_exact(quadruped: Genome) -> None:
    text = quadruped.model_dump_json()
    again = Genome.model_validate_json(text)
    assert again == quadruped
    assert again.model_dump_json() == text


def test_counts(quadruped: Genome) -> None:
    assert quadruped.num_limbs == 6
    assert quadruped.dof == 2 * 2 + 2 * 1 + 2 * 2
    assert [leaf.id for leaf in quadruped.leaves()] == [1, 2]


def _edit(genome: Genome, path: list, value: object) -> str:
    data = json.loads(genome.model_dump_json())
    node = data
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return json.dumps(data)


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        (["limbs", 0, "length"], 0.25, "limbs.0.length"),
        (["limbs", 0, "theta"], 30, "limbs.0.theta"),
        (["limbs", 0, "phi"], 45, "limbs.0.phi"),
        (["head_density"], 550, "head_density"),
        (["limbs", 0, "joints", 0, "range"], [-10, 10], "not one of the 13"),
        (["limbs", 0, "joints", 0, "gear"], 175, "gear"),
        (["limbs", 0, "joints", 0, "axis"], "z", "axis"),
        (["limbs", 2, "parent"], 9, "parent 9 does not exist"),
        (["limbs", 2, "site"], "head", "site 'head' is for limbs on the head"),
        (["limbs", 1, "id"], 0, "used twice"),
        (["limbs", 0, "paired"], False, "single limb must point within the sagittal plane"),
        (["limbs", 0, "colour"], "red", "Extra inputs are not permitted"),
    ],
)
def test_bad_genomes_are_rejected_clearly(
    quadruped: Genome, path: list, value: object, message: str
) -> None:
    with pytest.raises(ValidationError, match=message):
        Genome.model_validate_json(_edit(quadruped, path, value))


def test_cycle_is_rejected(quadruped: Genome) -> None:
    data = json.loads(quadruped.model_dump_json())
    data["limbs"][0].update(parent=2, site="end")
    with pytest.raises(ValidationError, match="cycle"):
        Genome.model_validate(data)


def test_more_than_ten_limbs_is_rejected(quadruped: Genome) -> None:
    data = json.loads(quadruped.model_dump_json())
    for i in range(3, 6):
        extra = dict(data["limbs"][1], id=i, parent=1, site="end", theta=90)
        data["limbs"].append(extra)
    with pytest.raises(ValidationError, match="12 limbs: at most 10"):
        Genome.model_validate(data)


def test_single_limb_on_a_mirrored_limb_is_rejected(quadruped: Genome) -> None:
    data = json.loads(quadruped.model_dump_json())
    data["limbs"][2]["paired"] = False
    with pytest.raises(ValidationError, match="single limb on mirrored limb"):
        Genome.model_validate(data)


def test_pair_on_the_plane_would_coincide(quadruped: Genome) -> None:
    with pytest.raises(ValidationError, match="twins coincide"):
        Genome.model_validate_json(_edit(quadruped, ["limbs", 0, "theta"], 180))


def test_limb_along_its_parent_from_its_mid_is_rejected(quadruped: Genome) -> None:
    data = json.loads(quadruped.model_dump_json())
    data["limbs"][2].update(site="mid", theta=45, phi=135)
    with pytest.raises(ValidationError, match="inside the parent"):
        Genome.model_validate(data)
