"""Package exports imported on first use (PEP 562), so that importing one light module of a
package (e.g. `derl.rl.config` for a message schema) does not import torch, scipy or matplotlib
through the package's ``__init__``."""

from __future__ import annotations

import importlib
from collections.abc import Callable


def exports(package: str, homes: dict[str, str]) -> Callable[[str], object]:
    """The module ``__getattr__`` of `package` whose names live in its submodules: `homes` maps
    each exported name to its submodule."""

    def __getattr__(name: str) -> object:
        if name not in homes:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{homes[name]}"), name)

    return __getattr__
