"""Morphological descriptors of a body (the paper's appendix D and fig. 3): mass, DoF, limbs,
bounding-box length/width/height, coverage, and passive stability."""

from __future__ import annotations

import math

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict

from derl.unimal.genome import Genome
from derl.unimal.geometry import bounding_box, layout
from derl.unimal.mjcf import FLOOR_OFFSET, agent_spec, rest_height, standalone_spec
from derl.unimal.space import HEAD_RADIUS, LIMB_RADIUS

STABILITY_STEPS = 400  # control steps, as the paper
FRAME_SKIP = 4
FALL_RATIO = 0.5
RESET_NOISE = 0.005  # uniform noise on every qpos and qvel, as the original environments


class Descriptors(BaseModel):
    """What a body looks like, in SI units; length is along +x (forward), width along y."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mass: float
    dof: int
    num_limbs: int
    length: float
    width: float
    height: float
    volume: float
    coverage: float
    passively_stable: bool
    stability_ratio: float


def describe(genome: Genome) -> Descriptors:
    """All descriptors of a body (compiles it and runs the 400-step stability test, ~50 ms)."""
    parts = layout(genome)
    low, high = bounding_box(parts)
    length, width, height = (high - low).tolist()
    volume = 4 / 3 * math.pi * HEAD_RADIUS**3 + sum(
        math.pi * LIMB_RADIUS**2 * (LIMB_RADIUS + p.limb.length) + 4 / 3 * math.pi * LIMB_RADIUS**3
        for p in parts
    )
    ratio = stability_ratio(genome)
    return Descriptors(
        mass=float(agent_spec(genome).compile().body_mass.sum()),
        dof=genome.dof,
        num_limbs=genome.num_limbs,
        length=length,
        width=width,
        height=height,
        volume=volume,
        coverage=volume / (length * width * height),
        passively_stable=ratio > FALL_RATIO,
        stability_ratio=ratio,
    )


def stability_ratio(genome: Genome, steps: int = STABILITY_STEPS) -> float:
    """Head height after `steps` control steps without control, over its resting height.

    The body starts as in the environments, its lowest point `FLOOR_OFFSET` above flat ground,
    with their small reset noise (fixed seed, so the answer is deterministic; without it a ball
    balanced on a vertical stick would stand forever); below 0.5 it has fallen (the same test
    ends an episode early), so the body is passively stable when this ratio stays above 0.5.
    """
    model = standalone_spec(genome, clearance=FLOOR_OFFSET).compile()
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    data.qpos[:] += rng.uniform(-RESET_NOISE, RESET_NOISE, model.nq)
    data.qvel[:] += rng.uniform(-RESET_NOISE, RESET_NOISE, model.nv)
    mujoco.mj_normalizeQuat(model, data.qpos)
    head = model.body("head").id
    mujoco.mj_step(model, data, nstep=steps * FRAME_SKIP)
    final = float(data.xpos[head, 2])
    return final / rest_height(layout(genome)) if np.isfinite(final) else 0.0
