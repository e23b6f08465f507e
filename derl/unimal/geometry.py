"""Rest-pose geometry of a genome: limb directions, body positions and joint axes, in numpy.

All body frames are aligned with the world at rest (bodies carry no rotation), so positions and
axes here are in the head's frame. A limb of length h points along d; its capsule runs from its
body origin to (r + h)·d, its mid site is at (r + h/2)·d, its end site at (r + h)·d and its tip at
(2r + h)·d; its body origin sits on its parent's surface (parent radius · d from the site) and its
hinges sit r behind the origin. Joint axes follow the paper: x or y of the limb frame whose z axis
points from the tip back to the joint (the minimal rotation of the world frame), and a mirror twin
gets the mirror image of each axis as a pseudovector, so equal controls give mirror motions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from derl.unimal.genome import Genome, Limb
from derl.unimal.space import HEAD_RADIUS, LIMB_RADIUS

MIRROR = np.array([1.0, -1.0, 1.0])


def direction(theta: float, phi: float) -> np.ndarray:
    """Unit vector for spherical angles in degrees (phi from +z, theta from +x towards +y)."""
    t, p = np.deg2rad(theta), np.deg2rad(phi)
    d = np.array([np.sin(p) * np.cos(t), np.sin(p) * np.sin(t), np.cos(p)])
    d[np.abs(d) < 1e-12] = 0.0
    return d


def limb_frame(d: np.ndarray) -> np.ndarray:
    """3x3 rotation whose z column is -d, the minimal rotation from the world frame."""
    v = -d
    k = np.array([-v[1], v[0], 0.0])  # e_z x v
    s2 = float(k @ k)
    if s2 < 1e-24:
        return np.eye(3)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + kx + kx @ kx * ((1.0 - v[2]) / s2)


def mirror_axis(axis: np.ndarray) -> np.ndarray:
    """The mirror image (y -> -y) of a rotation axis, a pseudovector."""
    return -MIRROR * axis


@dataclass(frozen=True)
class LimbPart:
    """One physical limb at rest: a genome entry, or the mirror twin of a paired entry."""

    name: str
    parent: str
    limb: Limb
    twin: bool
    direction: np.ndarray
    pos: np.ndarray  # body origin relative to the parent body origin
    origin: np.ndarray  # body origin relative to the head centre
    axes: tuple[np.ndarray, ...]

    def point(self, along: float) -> np.ndarray:
        """Body-frame point at distance `along` on the limb's axis."""
        return along * self.direction

    @property
    def mid(self) -> np.ndarray:
        return self.point(LIMB_RADIUS + self.limb.length / 2)

    @property
    def end(self) -> np.ndarray:
        return self.point(LIMB_RADIUS + self.limb.length)

    @property
    def tip(self) -> np.ndarray:
        return self.point(2 * LIMB_RADIUS + self.limb.length)


def part_name(limb_id: int, twin: bool) -> str:
    return f"limb{limb_id}_mirror" if twin else f"limb{limb_id}"


def layout(genome: Genome) -> list[LimbPart]:
    """Every physical limb of the body, parents before children."""
    parts: dict[str, LimbPart] = {}
    pending = list(genome.children(None))
    while pending:
        limb = pending.pop(0)
        for twin in (False, True) if limb.paired else (False,):
            parent = _parent_part(genome, parts, limb, twin)
            d = direction(limb.theta, limb.phi)
            frame = limb_frame(d)
            axes = tuple(frame[:, "xy".index(j.axis)] for j in limb.joints)
            if twin:
                d = MIRROR * d
                axes = tuple(mirror_axis(a) for a in axes)
            if parent is None:
                site, parent_radius, parent_origin, parent_name = (
                    np.zeros(3),
                    HEAD_RADIUS,
                    np.zeros(3),
                    "head",
                )
            else:
                site = parent.mid if limb.site == "mid" else parent.end
                parent_radius, parent_origin, parent_name = LIMB_RADIUS, parent.origin, parent.name
            pos = site + parent_radius * d
            name = part_name(limb.id, twin)
            parts[name] = LimbPart(name, parent_name, limb, twin, d, pos, parent_origin + pos, axes)
        pending.extend(genome.children(limb.id))
    return list(parts.values())


def _parent_part(
    genome: Genome, parts: dict[str, LimbPart], limb: Limb, twin: bool
) -> LimbPart | None:
    if limb.parent is None:
        return None
    on_twin = twin and genome.by_id[limb.parent].paired
    return parts[part_name(limb.parent, on_twin)]


def capsule_segments(parts: list[LimbPart]) -> tuple[np.ndarray, np.ndarray]:
    """(start, end) points of every limb capsule's axis, relative to the head centre."""
    starts = np.array([p.origin for p in parts]).reshape(-1, 3)
    ends = np.array([p.origin + p.end for p in parts]).reshape(-1, 3)
    return starts, ends


def bounding_box(parts: list[LimbPart]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned (low, high) corners of the whole body at rest, relative to the head centre."""
    starts, ends = capsule_segments(parts)
    low = np.minimum(starts, ends) - LIMB_RADIUS
    high = np.maximum(starts, ends) + LIMB_RADIUS
    low = np.vstack([low, np.full(3, -HEAD_RADIUS)]).min(axis=0)
    high = np.vstack([high, np.full(3, HEAD_RADIUS)]).max(axis=0)
    return low, high
