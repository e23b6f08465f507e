"""What pictures and clips of bodies look like: a daylight sky, a checkered ground, a sun.

Visual assets only: textures, a material and lights, none of which collides, weighs or moves
anything. The models that environments train on do not carry them; pictures (`standalone_spec`)
and clips (`derl.envs.video`) add them to models of their own.
"""

from __future__ import annotations

import mujoco

SKY_TOP = (0.36, 0.56, 0.84)
SKY_HORIZON = (0.86, 0.9, 0.95)
"""The sky's gradient, zenith to horizon; the horizon colour is also the haze's."""
GROUND = ((0.82, 0.8, 0.74), (0.64, 0.62, 0.57))
"""The checker's two colours: a light sand, so that the blue limbs stand out."""
GROUND_LINES = (0.45, 0.44, 0.4)
GROUND_SQUARE = 1.0
"""Side of a checker square, m: motion is read against it."""
GROUND_MATERIAL = "ground"
SUN_DIRECTION = (0.35, 0.6, -1.0)
"""From the sun towards the ground: high, from behind the camera's left."""
SPOT_HEIGHT = 5.0
"""Height of the shadow-casting spotlight over the body, m."""


def add_scenery(spec: mujoco.MjSpec, subject: mujoco.MjsBody) -> str:
    """The sky, the ground's material (its name, for the ground's geoms), and daylight on
    `subject`: a soft headlight, `add_lights`, haze the colour of the horizon."""
    add_sky(spec)
    spec.visual.headlight.ambient = [0.3, 0.3, 0.3]
    spec.visual.headlight.diffuse = [0.3, 0.3, 0.3]
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]
    spec.visual.rgba.fog = [*SKY_HORIZON, 1.0]
    add_lights(subject)
    return add_ground_material(spec)


def add_sky(spec: mujoco.MjSpec) -> None:
    """A gradient skybox: blue above, a pale haze at the horizon."""
    spec.add_texture(
        name="sky",
        type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
        rgb1=list(SKY_TOP),
        rgb2=list(SKY_HORIZON),
        width=256,
        height=256,
    )


def add_ground_material(spec: mujoco.MjSpec) -> str:
    """A checker of `GROUND_SQUARE` squares with darker edges, the same size on any geom
    (uniform texture mapping); its name."""
    spec.add_texture(
        name=GROUND_MATERIAL,
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        mark=mujoco.mjtMark.mjMARK_EDGE,
        rgb1=list(GROUND[0]),
        rgb2=list(GROUND[1]),
        markrgb=list(GROUND_LINES),
        width=256,
        height=256,
    )
    material = spec.add_material(  # uniform mapping: a square is 1 / texrepeat m
        name=GROUND_MATERIAL, texuniform=True, texrepeat=[1 / GROUND_SQUARE] * 2
    )
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = GROUND_MATERIAL
    return GROUND_MATERIAL


def add_lights(body: mujoco.MjsBody) -> None:
    """Daylight for a scene whose subject is `body`: a sun (a directional light, no shadow) and
    a spotlight high over the body that follows it without turning and casts its shadow (a
    shadow map covering only the ground around the body: sharp, and nothing beyond it)."""
    body.add_light(
        name="sun",
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM,
        dir=list(SUN_DIRECTION),
        diffuse=[0.4, 0.4, 0.37],
        specular=[0.1, 0.1, 0.1],
        castshadow=False,
    )
    body.add_light(
        name="shade",
        type=mujoco.mjtLightType.mjLIGHT_SPOT,
        mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM,
        pos=[SPOT_HEIGHT * d / SUN_DIRECTION[2] for d in SUN_DIRECTION[:2]] + [SPOT_HEIGHT],
        dir=list(SUN_DIRECTION),
        diffuse=[0.4, 0.4, 0.37],
        specular=[0.05, 0.05, 0.05],
        cutoff=50.0,
        exponent=1.0,
        castshadow=True,
    )
