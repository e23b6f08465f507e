"""The UNIMAL design space: the paper's table "Hyperparameters for UNIMAL design space"."""

from typing import TYPE_CHECKING, Final, Literal

MAX_LIMBS: Final = 10
HEAD_RADIUS: Final = 0.10
LIMB_RADIUS: Final = 0.05

LIMB_LENGTHS: Final = (0.2, 0.3, 0.4)
DENSITIES: Final = (500, 600, 700, 800, 900, 1000)
THETAS: Final = (0, 45, 90, 135, 180, 225, 270, 315)
PHIS: Final = (90, 135, 180)
GEARS: Final = (150, 200, 250, 300)
JOINT_RANGES: Final = (
    (-30, 0),
    (0, 30),
    (-30, 30),
    (-45, 45),
    (-45, 0),
    (0, 45),
    (-60, 0),
    (0, 60),
    (-60, 60),
    (-90, 0),
    (0, 90),
    (-60, 30),
    (-30, 60),
)
JOINT_AXES: Final = ("x", "y")
OPERATOR_NAMES: Final = (
    "grow_limb",
    "delete_limb",
    "limb_params",
    "density",
    "dof",
    "joint_angle",
    "gear",
)
"""The mutation operators (`derl.unimal.mutations.OPERATORS`), named here for what needs only
their names (a message's `mutation` field) and not MuJoCo."""
AXIS_SETS: Final = (("x",), ("y",), ("x", "y"))

if TYPE_CHECKING:  # a Literal takes no float for type checkers; pydantic checks the values
    LimbLength = float
else:
    LimbLength = Literal[0.2, 0.3, 0.4]
Density = Literal[500, 600, 700, 800, 900, 1000]
Theta = Literal[0, 45, 90, 135, 180, 225, 270, 315]
Phi = Literal[90, 135, 180]
Gear = Literal[150, 200, 250, 300]
Axis = Literal["x", "y"]
Site = Literal["head", "mid", "end"]
