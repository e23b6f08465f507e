"""The msgpack codec: a message to bytes and back, with one exception type for bad input.

`encode` packs `model_dump(mode="python")`: fields in declaration order (so equal messages give
equal bytes), bytes as msgpack bin, tuples as arrays. `decode` reads arrays back as tuples and
validates in strict mode (no "5" for 5, no text for bytes), and raises `DecodeError`, and nothing
else, for any payload that is not a valid message of this schema version.
"""

from __future__ import annotations

import reprlib
from typing import TypeVar, overload

import msgpack
from pydantic import TypeAdapter, ValidationError

from derl.messages.schema import SCHEMA_VERSION, Message, MessageBase

M = TypeVar("M", bound=MessageBase)

_MESSAGE: TypeAdapter[MessageBase] = TypeAdapter(Message)


class DecodeError(ValueError):
    """A payload that is not a valid message; the text says why."""


def encode(msg: MessageBase) -> bytes:
    return msgpack.packb(msg.model_dump(mode="python"), use_bin_type=True)


@overload
def decode(payload: bytes, expected: None = None) -> MessageBase: ...
@overload
def decode(payload: bytes, expected: type[M]) -> M: ...
def decode(payload: bytes, expected: type[M] | None = None) -> MessageBase:
    """The message in `payload`; with `expected`, it must be of that type."""
    try:
        raw = msgpack.unpackb(payload, use_list=False)
    except Exception as exc:  # msgpack raises many types for garbage: all mean the same here
        raise DecodeError(f"not msgpack: {exc!r}") from exc
    if not isinstance(raw, dict):
        raise DecodeError(f"not a map but {type(raw).__name__}")
    version = raw.get("schema_version")
    if version != SCHEMA_VERSION:
        raise DecodeError(f"schema version {reprlib.repr(version)}, expected {SCHEMA_VERSION}")
    try:
        msg = _MESSAGE.validate_python(raw, strict=True)
    except ValidationError as exc:
        raise DecodeError(_describe(exc, raw)) from exc
    except Exception as exc:  # a validator tripping over absurd input is still bad input
        raise DecodeError(f"invalid message: {exc!r}") from exc
    if expected is not None and not isinstance(msg, expected):
        raise DecodeError(f"expected {expected.__name__}, got {msg.type}")
    return msg


def _describe(exc: ValidationError, raw: dict[object, object]) -> str:
    errors = exc.errors(include_url=False, include_input=False)
    first = errors[0]
    if first["type"] == "union_tag_invalid":
        return f"unknown message type {reprlib.repr(raw.get('type'))}"
    if first["type"] == "union_tag_not_found":
        return "no message type"
    tag, *field = first["loc"]
    where = f"{'.'.join(map(str, field))}: " if field else ""
    more = f" (and {len(errors) - 1} more errors)" if len(errors) > 1 else ""
    return f"invalid {tag}: {where}{first['msg']}{more}"
