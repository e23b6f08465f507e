"""The paper's mutation operators. One operator per child, chosen uniformly among those that apply;
each attempt draws fresh random choices, the child must pass the full validity check, and an
operator that finds no valid child within `max_attempts` raises `MutationFailed`.

A child's `Genome.stand_height` follows the released code, whose bodies keep the head height of
their MJCF until an operator calls `set_head_pos`: `grow_limb` and `limb_params` do (the child
stands at its own resting height, None), `delete_limb` does not (the child keeps its parent's
height, `derl.unimal.mjcf.stand_height`), and the operators that change no shape (`density`,
`dof`, `joint_angle`, `gear`) keep the parent's field. `mutate(..., released_delete=False)`
gives every child its own resting height instead."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TypeVar, cast

import numpy as np
from pydantic import ValidationError

from derl.plugins import PluginError, Registry
from derl.unimal.genome import Genome, Joint, Limb
from derl.unimal.mjcf import stand_height
from derl.unimal.space import (
    AXIS_SETS,
    DENSITIES,
    GEARS,
    JOINT_RANGES,
    LIMB_LENGTHS,
    MAX_LIMBS,
    PHIS,
    THETAS,
)
from derl.unimal.validity import InvalidBody, check_body

MAX_ATTEMPTS = 50
MIN_LIMBS_TO_DELETE = 3
STAND_HEIGHT_DIGITS = 6  # a kept stand height is stored to the micrometre: one number everywhere

Direction = tuple[int, int]
"""(theta, phi) in degrees."""

# The distinct limb directions by where a new limb hangs (the design space, `derl.unimal.count`).
SAGITTAL_DIRECTIONS = ((0, 90), (180, 90), (0, 135), (180, 135), (0, 180))
PAIR_ON_SAGITTAL_DIRECTIONS = tuple((t, p) for t in (45, 90, 135) for p in (90, 135))
PAIR_ON_PAIR_DIRECTIONS = (*((t, p) for t in THETAS for p in PHIS if p != 180), (0, 180))


class MutationFailed(RuntimeError):
    """No valid child was found: the operator, the attempts and the last reason."""

    def __init__(self, op: str, attempts: int, reason: str) -> None:
        super().__init__(f"{op} found no valid child in {attempts} attempts; last: {reason}")
        self.op = op
        self.attempts = attempts
        self.reason = reason


@dataclass(frozen=True)
class Mutation:
    """What was done to make a child: the operator and a human-readable detail."""

    op: str
    detail: str


Operator = Callable[[Genome, np.random.Generator], tuple[Genome, str]]


T = TypeVar("T")


def _pick(rng: np.random.Generator, items: Sequence[T]) -> T:
    return items[int(rng.integers(len(items)))]


def random_joint(rng: np.random.Generator, axis: str) -> Joint:
    return Joint(axis=axis, range=_pick(rng, JOINT_RANGES), gear=_pick(rng, GEARS))


def random_joints(rng: np.random.Generator) -> tuple[Joint, ...]:
    return tuple(random_joint(rng, axis) for axis in _pick(rng, AXIS_SETS))


def _with(genome: Genome, **changes: object) -> Genome:
    """A validated copy of `genome` with some fields changed."""
    fields = {name: getattr(genome, name) for name in Genome.model_fields}
    return Genome(**{**fields, **changes})


def _replaced(genome: Genome, limb: Limb, **changes: object) -> tuple[Limb, ...]:
    """`genome`'s limb entries with one entry changed (validated)."""
    new = Limb(**{**dict(limb), **changes})
    return tuple(new if item.id == limb.id else item for item in genome.limbs)


def grow_limb(genome: Genome, rng: np.random.Generator) -> tuple[Genome, str]:
    """One attempt of the released code's `grow_limb`: a site drawn uniformly among every
    physical limb's mid and end and the head centre; one limb or a mirror pair on a sagittal
    site (even chances), a pair on a mirrored one; theta (8 values) and phi (3) drawn once,
    independently (phi 180 points straight down whatever theta; a pair on a sagittal site takes
    a theta beyond 180 as its twin's, 360 - theta). The genome's rules reject what the site does
    not allow (a single limb off the sagittal plane, a pair in it, a limb along its parent, more
    than 10 limbs), and `mutate` then makes a new attempt from scratch, at a new site."""
    sites: list[tuple[int | None, str]] = [(None, "head")]
    for limb in genome.limbs:
        sites += [(limb.id, "mid"), (limb.id, "end")] * limb.count
    parent, site = _pick(rng, sites)
    sagittal = genome.is_sagittal(parent)
    paired = bool(rng.integers(2)) if sagittal else True
    theta, phi = _pick(rng, THETAS), _pick(rng, PHIS)
    if phi == 180:
        theta = 0
    elif paired and sagittal and theta > 180:
        theta = 360 - theta
    new = Limb(
        id=genome.next_id(),
        parent=parent,
        site=site,
        paired=paired,
        length=_pick(rng, LIMB_LENGTHS),
        theta=theta,
        phi=phi,
        joints=random_joints(rng),
    )
    child = _with(genome, limbs=(*genome.limbs, new), stand_height=None)
    where = "head" if parent is None else f"{site} of limb {parent}"
    return child, f"{'pair' if paired else 'limb'} {new.id} at {where}"


def delete_limb(genome: Genome, rng: np.random.Generator) -> tuple[Genome, str]:
    """Remove a leaf limb (or leaf pair); the child keeps its parent's stand height (the
    released code's `mutate_delete_limb` does not call `set_head_pos`)."""
    leaf = _pick(rng, genome.leaves())
    limbs = tuple(limb for limb in genome.limbs if limb.id != leaf.id)
    height = round(stand_height(genome), STAND_HEIGHT_DIGITS)
    return _with(genome, limbs=limbs, stand_height=height), f"limb {leaf.id}"


def limb_params(genome: Genome, rng: np.random.Generator) -> tuple[Genome, str]:
    """Give a limb (or pair) a length drawn anew (it may come out as it was: the released code);
    its children move with its sites."""
    limb = _pick(rng, genome.limbs)
    length = _pick(rng, LIMB_LENGTHS)
    child = _with(genome, limbs=_replaced(genome, limb, length=length), stand_height=None)
    return child, f"limb {limb.id} length {length}"


def density(genome: Genome, rng: np.random.Generator) -> tuple[Genome, str]:
    """New densities for the limbs and for the head, each drawn anew (either may come out as it
    was: the released code)."""
    limbs, head = _pick(rng, DENSITIES), _pick(rng, DENSITIES)
    return _with(genome, limb_density=limbs, head_density=head), f"limbs {limbs}, head {head}"


def _mutate_joints(
    genome: Genome, rng: np.random.Generator, redraw: Callable[[Limb], tuple[Joint, ...]]
) -> tuple[Genome, str]:
    """New hinges (`redraw`) for every limb entry (a limb or a pair) with probability 1/2, else
    for one drawn entry: the released code's `mutate_joint`. The values are drawn anew, so a
    hinge may come out as it was."""
    chosen = genome.limbs if rng.integers(2) else (_pick(rng, genome.limbs),)
    new = {limb.id: Limb(**{**dict(limb), "joints": redraw(limb)}) for limb in chosen}
    child = _with(genome, limbs=tuple(new.get(limb.id, limb) for limb in genome.limbs))
    return child, f"limb{'s' * (len(new) > 1)} {', '.join(map(str, new))}"


def dof(genome: Genome, rng: np.random.Generator) -> tuple[Genome, str]:
    """New hinges, their axes drawn anew, with new ranges and gears."""
    return _mutate_joints(genome, rng, lambda _: random_joints(rng))


def _redrawn(
    rng: np.random.Generator, field: str, options: Sequence[object]
) -> Callable[[Limb], tuple[Joint, ...]]:
    """A limb's hinges, each with `field` drawn anew from `options`."""
    return lambda limb: tuple(Joint(**{**dict(j), field: _pick(rng, options)}) for j in limb.joints)


def joint_angle(genome: Genome, rng: np.random.Generator) -> tuple[Genome, str]:
    """A new range for every hinge (of one limb entry, or of all)."""
    return _mutate_joints(genome, rng, _redrawn(rng, "range", JOINT_RANGES))


def gear(genome: Genome, rng: np.random.Generator) -> tuple[Genome, str]:
    """A new motor gear for every hinge (of one limb entry, or of all)."""
    return _mutate_joints(genome, rng, _redrawn(rng, "gear", GEARS))


OPERATORS: dict[str, Operator] = {
    "grow_limb": grow_limb,
    "delete_limb": delete_limb,
    "limb_params": limb_params,
    "density": density,
    "dof": dof,
    "joint_angle": joint_angle,
    "gear": gear,
}


def _operator(loaded: object) -> Operator:
    if not callable(loaded):
        raise TypeError(f"{loaded!r} is not callable")
    return cast(Operator, loaded)


OPERATOR_REGISTRY: Registry[Operator] = Registry("operator", "derl.operators", OPERATORS, _operator)
"""Every mutation operator by name: the seven built-ins and the plugins. A plugin operator is a
function ``(genome, rng) -> (child, detail)`` like the built-ins; an ``applies`` attribute, a
function ``genome -> bool``, says which bodies it acts on (else every body)."""


def applicable(genome: Genome, weights: Mapping[str, float] | None = None) -> list[str]:
    """The operators that can act on this genome: of the built-ins (None), or of those with a
    positive weight in `weights` (the built-ins in their order first, then the plugins in the
    order given)."""
    if weights is not None:
        builtin = set(applicable(genome))
        order = list(dict.fromkeys([*OPERATORS, *weights]))
        named = sorted(weights, key=order.index)
        return [op for op in named if weights[op] > 0 and _applies(op, genome, builtin)]
    if not genome.limbs:
        return ["grow_limb"]
    ops = [op for op in OPERATORS if op not in ("grow_limb", "delete_limb")]
    if genome.num_limbs < MAX_LIMBS:
        ops.append("grow_limb")
    if genome.num_limbs >= MIN_LIMBS_TO_DELETE:
        ops.append("delete_limb")
    return sorted(ops, key=list(OPERATORS).index)


def _applies(op: str, genome: Genome, builtin: set[str]) -> bool:
    if op in OPERATORS:
        return op in builtin
    test = getattr(OPERATOR_REGISTRY.get(op), "applies", None)
    if test is None:
        return True
    try:
        return bool(test(genome))
    except Exception as error:  # a plugin may raise anything
        raise PluginError(f"operator {op!r}: its applies() raised {_error(error)}") from None


def _draw(rng: np.random.Generator, ops: list[str], weights: Mapping[str, float] | None) -> str:
    """An operator among `ops` with probability in proportion to its weight (uniformly, by the
    paper's draw, when the weights are equal)."""
    if weights is None or len({weights[op] for op in ops}) <= 1:
        return _pick(rng, ops)
    shares = np.array([weights[op] for op in ops], dtype=np.float64)
    return ops[int(rng.choice(len(ops), p=shares / shares.sum()))]


def _error(error: BaseException) -> str:
    return f"{type(error).__name__}: {error}"


def mutate(
    genome: Genome,
    rng: np.random.Generator,
    op: str | None = None,
    max_attempts: int = MAX_ATTEMPTS,
    check: Callable[[Genome], None] = check_body,
    released_delete: bool = True,
    weights: Mapping[str, float] | None = None,
) -> tuple[Genome, Mutation]:
    """A valid child of `genome` made by one operator (drawn if not given: uniformly among the
    built-ins that apply, the paper's choice, or by `weights` among the operators they name,
    plugins included); `check` raises `InvalidBody` for a body that cannot exist.
    ``released_delete``: the child's stand height as the released code leaves it (a
    `delete_limb` child keeps its parent's; see the module's docstring); False: every child
    stands at its own resting height. A plugin operator that raises, or returns anything but a
    (genome, detail) pair, is a `PluginError` naming it; one whose bodies fail the validity check
    is retried like a built-in and then a `MutationFailed` naming it."""
    ops = applicable(genome, weights)
    if not ops:
        raise MutationFailed("every weighted operator", 0, "none applies to this body")
    if op is None:
        op = _draw(rng, ops, weights)
    elif op not in ops:
        raise MutationFailed(op, 0, f"{op} does not apply to a body with {genome.num_limbs} limbs")
    operator = OPERATOR_REGISTRY.get(op)
    reason = ""
    for _ in range(max_attempts):
        try:
            if op in OPERATORS:
                child, detail = operator(genome, rng)
            else:
                child, detail = _plugin_child(op, operator, genome, rng)
            check(child)
        except ValidationError as error:  # structurally impossible (e.g. more than 10 limbs)
            reason = error.errors()[0]["msg"]
            continue
        except InvalidBody as error:  # physically impossible (self-intersection)
            reason = str(error)
            continue
        if not released_delete and child.stand_height is not None:
            child = child.model_copy(update={"stand_height": None})
        return child, Mutation(op, detail)
    raise MutationFailed(op, max_attempts, reason)


def _plugin_child(
    op: str, operator: Operator, genome: Genome, rng: np.random.Generator
) -> tuple[Genome, str]:
    """A plugin operator's child, checked: a body it could not make is its `ValidationError` or
    `InvalidBody` (an attempt that failed); anything else it raises or returns is a
    `PluginError` naming it."""
    try:
        made: object = operator(genome, rng)
    except (ValidationError, InvalidBody):
        raise
    except Exception as error:  # a plugin may raise anything
        raise PluginError(f"operator {op!r} raised {_error(error)}") from None
    if (
        not isinstance(made, tuple)
        or len(made) != 2
        or not isinstance(made[0], Genome)
        or not isinstance(made[1], str)
    ):
        raise PluginError(f"operator {op!r} returned {made!r:.80}, not a (Genome, str) pair")
    return made[0], made[1]
