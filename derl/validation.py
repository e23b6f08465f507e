"""A pydantic validation error as the one line a user reads: `field: reason; ...`."""

from __future__ import annotations

from pydantic import ValidationError


def problems(error: ValidationError, names: dict[str, str] | None = None) -> str:
    """Every problem of `error` in one line, each after its field's location (renamed by
    `names`, e.g. to a command's option)."""
    names = names or {}
    reasons = []
    for item in error.errors():
        where = ".".join(names.get(str(part), str(part)) for part in item["loc"])
        reason = item["msg"].removeprefix("Value error, ")
        reasons.append(f"{where}: {reason}" if where else reason)
    return "; ".join(reasons)
