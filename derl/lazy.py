"""Package exports imported on first use (PEP 562), so that importing one light module of a
package (e.g. `derl.rl.config` for a message schema) does not import torch, scipy or matplotlib
through the package's ``__init__``."""

from __future__ import annotations

import importlib
from collections.abc import Callable


def exports(
    package: str, modules: dict[str, tuple[str, ...]]
) -> tuple[Callable[[str], object], list[str]]:
    """The module ``__getattr__`` and ``__all__`` of `package`, whose names live in its
    submodules: `modules` maps each submodule to the names it exports."""
    homes = {name: module for module, names in modules.items() for name in names}

    def __getattr__(name: str) -> object:
        if name not in homes:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{homes[name]}"), name)

    return __getattr__, sorted(homes)
