"""Compiled bodies: geometry, true mirror twins, validity checks, exclusions, descriptors."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from derl.unimal import Genome, InvalidBody, Joint, Limb, agent_spec, check_body, describe
from derl.unimal.descriptors import stability_ratio
from derl.unimal.geometry import direction, layout, limb_frame
from derl.unimal.mjcf import rest_height, to_mjcf
from derl.unimal.space import HEAD_RADIUS, LIMB_RADIUS

MIRROR = np.array([1.0, -1.0, 1.0])
ONE = (Joint(axis="x", range=(-30, 30), gear=150),)


def test_limb_frame_matches_the_original_convention() -> None:
    # A limb along -x: its frame's x axis is -z (so "x" is a yaw) and its y axis is +y.
    frame = limb_frame(direction(180, 90))
    np.testing.assert_allclose(frame[:, 0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(frame[:, 1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(limb_frame(direction(0, 180)), np.eye(3))


def test_geometry_of_a_limb_on_the_head() -> None:
    genome = Genome(
        head_density=500,
        limb_density=500,
        limbs=(Limb(id=0, length=0.4, theta=0, phi=180, joints=ONE),),
    )
    (part,) = layout(genome)
    np.testing.assert_allclose(part.pos, [0, 0, -0.1])
    np.testing.assert_allclose(part.tip, [0, 0, -0.5])
    model = agent_spec(genome).compile()
    assert model.body("head").pos[2] == pytest.approx(0.1 + 0.05 + 0.45)  # lowest point at z=0
    head_mass = 500 * 4 / 3 * math.pi * 0.1**3
    limb_mass = 500 * (math.pi * 0.05**2 * 0.45 + 4 / 3 * math.pi * 0.05**3)
    assert model.body_mass.sum() == pytest.approx(head_mass + limb_mass, rel=1e-6)


def _primary(name: str) -> str:
    return name.replace("_mirror", "")


def test_twins_are_true_mirror_images(quadruped: Genome) -> None:
    """Equal controls on both members of every pair give mirror-image motion (y -> -y)."""
    model = agent_spec(quadruped).compile()
    model.opt.gravity[:] = 0
    data = mujoco.MjData(model)
    twin_of = {i: model.actuator(_primary(model.actuator(i).name)).id for i in range(model.nu)}
    rng = np.random.default_rng(0)
    for _ in range(200):
        ctrl = rng.uniform(-1, 1, model.nu)
        data.ctrl[:] = ctrl[list(twin_of.values())]
        mujoco.mj_step(model, data)
    assert np.abs(data.qvel[6:]).max() > 0.1  # the limbs really moved
    twins = [b for b in range(model.nbody) if model.body(b).name.endswith("_mirror")]
    assert len(twins) == 3
    for body in twins:
        primary = model.body(_primary(model.body(body).name)).id
        np.testing.assert_allclose(data.xpos[body], MIRROR * data.xpos[primary], atol=1e-6)
        np.testing.assert_allclose(data.xquat[body][[0, 2]], data.xquat[primary][[0, 2]], atol=1e-6)
        for joint in np.flatnonzero(model.jnt_bodyid == body):
            other = model.joint(_primary(model.joint(joint).name)).id
            np.testing.assert_allclose(data.xaxis[joint], -MIRROR * data.xaxis[other], atol=1e-6)
            assert model.jnt_range[joint].tolist() == model.jnt_range[other].tolist()
            assert data.qpos[model.jnt_qposadr[joint]] == pytest.approx(
                data.qpos[model.jnt_qposadr[other]], abs=1e-6
            )
    assert abs(data.subtree_com[model.body("head").id, 1]) < 1e-6


def test_model_has_motors_sensors_and_sites(quadruped: Genome) -> None:
    model = agent_spec(quadruped).compile()
    assert model.nu == quadruped.dof
    assert model.actuator_ctrlrange.tolist() == [[-1.0, 1.0]] * model.nu
    assert sorted(set(model.actuator_gear[:, 0].tolist())) == [150.0, 200.0]
    names = {model.sensor(i).name for i in range(model.nsensor)}
    assert {"head_accel", "head_gyro", "head_vel", "head_touch"} <= names
    assert {f"limb{i}_touch" for i in range(3)} <= names
    assert {f"limb{i}_mirror_end_pos" for i in range(3)} <= names
    for part in layout(quadruped):
        for site in ("mid", "end", "tip", "touch"):
            model.site(f"{part.name}_{site}")


def test_exclusions_survive_a_saved_mjcf(quadruped: Genome) -> None:
    # parent-child pairs (6) plus the two pairs grown together on the head
    model = mujoco.MjModel.from_xml_string(to_mjcf(quadruped))
    assert model.nexclude == 6 + 2
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    self_contacts = [c for c in data.contact[: data.ncon] if model.geom(c.geom1).name != "floor"]
    assert not self_contacts


def test_touching_siblings_are_invalid() -> None:
    genome = Genome(
        head_density=500,
        limb_density=500,
        limbs=(
            Limb(id=0, length=0.3, theta=0, phi=90, joints=ONE),
            Limb(id=1, length=0.3, theta=0, phi=135, joints=ONE),
        ),
    )
    with pytest.raises(InvalidBody, match="self-intersection at rest: limb0-limb1"):
        check_body(genome)


def test_descriptors_of_a_pole_and_a_quadruped(quadruped: Genome) -> None:
    pole = Genome(
        head_density=1000,
        limb_density=1000,
        limbs=(Limb(id=0, length=0.4, theta=0, phi=180, joints=ONE),),
    )
    d = describe(pole)
    assert (d.length, d.width, d.height) == pytest.approx((0.2, 0.2, 0.7))
    assert d.coverage == pytest.approx(d.volume / (0.2 * 0.2 * 0.7))
    assert not d.passively_stable  # a ball on a stick falls over
    q = describe(quadruped)
    assert q.num_limbs == 6 and q.dof == 10
    # the upper legs point 45 degrees off the y axis: each ends (head + limb radius + 0.3) / 2 out
    # in y, its lower leg hangs straight down from there, one limb radius thick
    assert q.width == pytest.approx(HEAD_RADIUS + 3 * LIMB_RADIUS + 0.3)  # 0.55
    assert 0 < q.coverage < 1
    # the stability test starts the body as the environments do: 0.2 m up, then it drops
    rest = rest_height(layout(quadruped))
    assert stability_ratio(quadruped, steps=1) == pytest.approx((rest + 0.2) / rest, abs=0.02)
