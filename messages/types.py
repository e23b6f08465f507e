"""Constrained field types shared by the messages: safe ids, bounded counts, checked floats.

Ids become Zenoh key segments, so they are restricted to ``[A-Za-z0-9_.-]`` (no ``/``, ``*``,
``$``, ``?``, ``#``, never empty). Floats are finite, except a `Measure`: a quantity that can be
missing (energy with no finished episode, cost of work with no forward progress) is NaN there.
"""

from __future__ import annotations

import math
from typing import Annotated, Final

from pydantic import AfterValidator, Field

ID_PATTERN: Final = r"^[A-Za-z0-9_.-]{1,128}$"
"""The one definition of a safe id (and key segment), used by the models and by the key space."""

MAX_STEPS: Final = 10**13
MAX_ITEMS: Final = 1_000_000
MAX_CHECKPOINT_BYTES: Final = 8 * 2**20
"""A checkpoint's bound: the largest real one, a 10-limb body's network in VT, is about 1 MB."""
MAX_MESSAGE_BYTES: Final = 16 * 2**20
"""The largest message a derl session takes (Zenoh's `transport/link/rx/max_message_size`, 1 GiB
by default): a margin above the largest real one (a FitnessReport with its checkpoint), so a
larger sample is dropped by the transport before it is assembled in memory."""


def _missing_or_non_negative(value: float) -> float:
    if math.isnan(value) or 0 <= value < math.inf:
        return value
    raise ValueError("must be finite and >= 0, or NaN when missing")


Id = Annotated[str, Field(pattern=ID_PATTERN)]
Count = Annotated[int, Field(ge=0, le=MAX_STEPS)]
Steps = Annotated[int, Field(ge=1, le=MAX_STEPS)]
Seed = Annotated[int, Field(ge=0, le=2**64 - 1)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Measure = Annotated[float, AfterValidator(_missing_or_non_negative)]
Text = Annotated[str, Field(max_length=1000)]
