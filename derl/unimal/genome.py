"""The UNIMAL genome: a kinematic tree of a sphere head and capsule limbs, symmetric by design.

A `Limb` entry is either one limb on the sagittal plane (``paired=False``) or a mirror pair
(``paired=True``): the stored orientation belongs to the primary limb and its twin is its mirror
image (y -> -y). A pair grown on a sagittal parent hangs from the same site of that parent; a pair
grown on a pair hangs its primary from the parent's primary and its twin from the parent's twin.
Everything here is checked without MuJoCo, so a bad genome is rejected before any compile.
"""

from __future__ import annotations

from functools import cached_property
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from derl.unimal.space import (
    JOINT_RANGES,
    MAX_LIMBS,
    Axis,
    Density,
    Gear,
    LimbLength,
    Phi,
    Site,
    Theta,
)


class Joint(BaseModel):
    """A motor-actuated hinge between a limb and its parent, about the limb frame's x or y axis."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    axis: Axis
    """The limb-frame axis the hinge turns about."""
    range: tuple[int, int]
    """Joint limits in degrees: one of the design space's 13 pairs."""
    gear: Gear
    """The motor's gear (torque per unit of control)."""

    @field_validator("range")
    @classmethod
    def _range_in_table(cls, value: tuple[int, int]) -> tuple[int, int]:
        if value not in JOINT_RANGES:
            raise ValueError(f"joint range {list(value)} is not one of the 13 of the design space")
        return value


class Limb(BaseModel):
    """One sagittal limb, or a mirror pair of limbs, attached to the head or to a limb's mid/end."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    id: Annotated[int, Field(ge=0)]
    """The entry's id."""
    parent: Annotated[int, Field(ge=0)] | None = None
    """The limb it hangs from (None: the head)."""
    site: Site = "head"
    """Where on its parent: the head's centre, or a limb's mid or end."""
    paired: bool = False
    """A mirror pair (y -> -y) rather than one limb on the sagittal plane."""
    length: LimbLength
    """Capsule length, m."""
    theta: Theta
    """Direction: degrees from +x towards +y."""
    phi: Phi
    """Direction: degrees from +z (180: straight down)."""
    joints: tuple[Joint, ...]
    """Its hinges: about x, y, or x then y."""

    @model_validator(mode="after")
    def _consistent(self) -> Limb:
        if (self.parent is None) != (self.site == "head"):
            raise ValueError(
                f"limb {self.id}: site 'head' is for limbs on the head (parent null), "
                f"'mid'/'end' for limbs on a limb; got parent={self.parent} site={self.site!r}"
            )
        if self.phi == 180 and self.theta != 0:
            raise ValueError(f"limb {self.id}: phi=180 points straight down; theta must be 0")
        axes = [j.axis for j in self.joints]
        if axes not in (["x"], ["y"], ["x", "y"]):
            raise ValueError(f"limb {self.id}: joints must be about x, y, or x then y; got {axes}")
        return self

    @property
    def count(self) -> int:
        """Number of physical limbs this entry stands for."""
        return 2 if self.paired else 1

    @property
    def sagittal_direction(self) -> bool:
        """Whether the limb points within the sagittal (x-z) plane."""
        return self.theta % 180 == 0 or self.phi == 180


class Genome(BaseModel):
    """A whole body: head density, the shared limb density and the limbs."""

    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    head_density: Density
    """Density of the head sphere, kg/m³."""
    limb_density: Density
    """Density of every limb, kg/m³."""
    limbs: tuple[Limb, ...] = ()
    """The limb entries (at most 10 limbs in all, a pair counting 2)."""
    stand_height: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    """The head's height (m) above the ground that the environments take as the body's resting
    height in place of its own (None: its own, `derl.unimal.mjcf.rest_height`): the head spawns
    that high plus the spawn clearance, and the body has fallen when the head is below a fraction
    of it. Set where the released code keeps a parent's height (`derl.unimal.mutations`)."""

    @model_validator(mode="after")
    def _valid_tree(self) -> Genome:
        by_id: dict[int, Limb] = {}
        for limb in self.limbs:
            if limb.id in by_id:
                raise ValueError(f"limb id {limb.id} is used twice")
            by_id[limb.id] = limb
        if self.num_limbs > MAX_LIMBS:
            raise ValueError(f"{self.num_limbs} limbs: at most {MAX_LIMBS} are allowed")
        for limb in self.limbs:
            if limb.parent is not None and limb.parent not in by_id:
                raise ValueError(f"limb {limb.id}: parent {limb.parent} does not exist")
        for limb in self.limbs:
            seen = {limb.id}
            node = limb
            while node.parent is not None:
                if node.parent in seen:
                    raise ValueError(f"limb {limb.id}: the parents form a cycle {sorted(seen)}")
                seen.add(node.parent)
                node = by_id[node.parent]
        for limb in self.limbs:
            _check_symmetry(limb, by_id.get(limb.parent) if limb.parent is not None else None)
        return self

    @cached_property
    def by_id(self) -> dict[int, Limb]:
        return {limb.id: limb for limb in self.limbs}

    @property
    def num_limbs(self) -> int:
        return sum(limb.count for limb in self.limbs)

    @property
    def dof(self) -> int:
        return sum(limb.count * len(limb.joints) for limb in self.limbs)

    def children(self, limb_id: int | None) -> list[Limb]:
        """Limb entries attached to `limb_id` (None: the head)."""
        return [limb for limb in self.limbs if limb.parent == limb_id]

    def is_sagittal(self, limb_id: int | None) -> bool:
        """Whether a part lies on the sagittal plane (the head, or an unpaired limb)."""
        return limb_id is None or not self.by_id[limb_id].paired

    def leaves(self) -> list[Limb]:
        parents = {limb.parent for limb in self.limbs}
        return [limb for limb in self.limbs if limb.id not in parents]

    def next_id(self) -> int:
        return max((limb.id for limb in self.limbs), default=-1) + 1


def _check_symmetry(limb: Limb, parent: Limb | None) -> None:
    """Rules that make the body bilaterally symmetric and its limbs geometrically sensible."""
    parent_sagittal = parent is None or not parent.paired
    if not limb.paired:
        if not parent_sagittal:
            raise ValueError(f"limb {limb.id}: a single limb on mirrored limb {limb.parent}")
        if not limb.sagittal_direction:
            raise ValueError(
                f"limb {limb.id}: a single limb must point within the sagittal plane "
                f"(theta 0 or 180, or phi 180); got theta={limb.theta} phi={limb.phi}"
            )
    elif parent_sagittal and limb.sagittal_direction:
        raise ValueError(
            f"limb {limb.id}: a mirror pair on a sagittal site must point off the plane, "
            f"else the twins coincide; got theta={limb.theta} phi={limb.phi}"
        )
    if parent is None:
        return
    same = (limb.theta, limb.phi) == (parent.theta, parent.phi)
    opposite = limb.phi == parent.phi == 90 and (limb.theta - parent.theta) % 360 == 180
    if opposite or (same and limb.site == "mid"):
        raise ValueError(
            f"limb {limb.id}: pointing along its parent {parent.id} from its {limb.site} "
            "would put it inside the parent"
        )
