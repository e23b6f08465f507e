"""The one way derl acts on a message by its type: methods marked `@handles(Type, ...)`.

A class that takes messages subclasses `Handler` and marks each of its handlers with the message
types it takes; `dispatch(msg, *args)` calls the handler of `type(msg)` with `msg` and `args` and
returns what it returns (None for a type the class does not handle). The table maps a type to a
method's name, so a subclass extends a handler by defining the method again under the same name
(calling `super()`), and the most derived one runs. The coordinator's loop, the journal's fold
(`RunHistory` and the coordinator's state), the monitor and the Foxglove bridge all dispatch so.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, TypeVar

from derl.messages.schema import MessageBase

Method = TypeVar("Method", bound=Callable[..., Any])

_TYPES = "_derl_handles"


def handles(*types: type[MessageBase]) -> Callable[[Method], Method]:
    """Mark a method as the handler of messages of `types`."""

    def mark(method: Method) -> Method:
        setattr(method, _TYPES, types)
        return method

    return mark


class Handler:
    """A class whose marked methods take messages (`dispatch`)."""

    _handlers: ClassVar[dict[type[MessageBase], str]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        table: dict[type[MessageBase], str] = {}
        for klass in reversed(cls.__mro__):
            for name, value in vars(klass).items():
                for kind in getattr(value, _TYPES, ()):
                    table[kind] = name
        cls._handlers = table

    def dispatch(self, msg: MessageBase, *args: Any) -> Any:
        """Call the handler of `msg`'s type with `msg` and `args`; what it returns (None
        without one)."""
        name = self._handlers.get(type(msg))
        return None if name is None else getattr(self, name)(msg, *args)
