"""Extension points: registries of named pieces a researcher adds from their own package, and
what identifies such a plugin on every node.

A `Registry` holds derl's built-in pieces of one kind (tasks, selection schemes, mutation
operators) and finds more the way Gymnasium's and MuJoCo Playground's registries do, in two ways:

- an **entry point** of an installed package in the registry's group, by its name::

      [project.entry-points."derl.tasks"]
      stairs = "my_study.stairs:stairs"

- a **spec** written where a name is expected: ``my_study.stairs:stairs`` (or the dotted form
  ``my_study.stairs.stairs``, which the profile keeps: it is a safe key segment on the bus).

A built-in name always means the built-in piece. A plugin's identity (`Plugin`: its name, where
it is defined, its distribution and version, and a hash of its source) travels in every job, so
a node that holds another version refuses the job (`check_plugins`), and a run's fingerprint
covers it. Nothing here imports a plugin before it is asked for.
"""

from __future__ import annotations

import hashlib
import importlib
import pkgutil
import sys
from collections.abc import Callable, Iterable, Mapping
from functools import cache
from importlib.metadata import EntryPoint, entry_points, packages_distributions, version
from pathlib import Path
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict, Field

T = TypeVar("T")

SPEC_PATTERN = r"^[A-Za-z0-9_.-]{1,128}$"
"""A piece's name as a profile keeps it and a job carries it (a safe key segment)."""


def canonical(name: str) -> str:
    """`name` as a profile keeps it and a job carries it: a spec's ``module:name`` becomes
    ``module.name`` (both load the same piece)."""
    return name.replace(":", ".")


class PluginError(ValueError):
    """A plugin cannot be found, loaded or used: the whole reason in one line."""


class Plugin(BaseModel):
    """What identifies a plugin: the same identity on two nodes means the same code.

    ``source`` is a SHA-256 of the source files of the package that defines it (every ``.py``
    file under its top-level package, or its one module), so an edit that is not released as a
    new version is seen too."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: str = Field(pattern=r"^[a-z_]{1,32}$")
    """The extension point: task, selection or operator."""
    name: str = Field(pattern=SPEC_PATTERN)
    """As the profile names it."""
    target: str = Field(max_length=256)
    """``module:attribute`` of the piece."""
    distribution: str = Field("", max_length=128)
    """The installed distribution that holds it ('' for a module on the path only)."""
    version: str = Field("", max_length=64)
    """That distribution's version ('' if none)."""
    source: str = Field(pattern=r"^[0-9a-f]{64}$")
    """SHA-256 of its package's source files."""

    def describe(self) -> str:
        """One line: ``name (distribution version, source abcd1234)``."""
        release = f"{self.distribution} {self.version}".strip() or "no distribution"
        return f"{self.name} ({release}, source {self.source[:8]})"


class Registry(Generic[T]):
    """The pieces of one kind: built-ins by name, then the installed packages' entry points in
    `group`, then specs (``module:name``). `check` turns what was loaded into a piece or raises
    `PluginError`'s reason (a `TypeError`/`ValueError` message)."""

    def __init__(
        self,
        kind: str,
        group: str,
        builtins: Mapping[str, T],
        check: Callable[[object], T],
    ) -> None:
        self.kind, self.group = kind, group
        self.builtins = dict(builtins)
        self._check = check
        self._loaded: dict[str, T] = {}

    def installed(self) -> dict[str, EntryPoint]:
        """The entry points of installed packages in this registry's group, by name (one named
        like a built-in is never used)."""
        return {
            ep.name: ep for ep in entry_points(group=self.group) if ep.name not in self.builtins
        }

    def names(self) -> list[str]:
        """Every name this registry knows without a spec: built-ins, then installed plugins."""
        return [*self.builtins, *sorted(self.installed())]

    def get(self, name: str) -> T:
        """The piece called `name` (`PluginError` saying why there is none)."""
        if name in self.builtins:
            return self.builtins[name]
        if name not in self._loaded:
            self._loaded[name] = self._load(name)
        return self._loaded[name]

    def identity(self, name: str) -> Plugin | None:
        """`name`'s plugin identity (None for a built-in)."""
        if name in self.builtins:
            return None
        self.get(name)
        target = self._target(name)
        distribution, version = _distribution(target, self.installed().get(name))
        return Plugin(
            kind=self.kind,
            name=canonical(name),
            target=target,
            distribution=distribution,
            version=version,
            source=_source_hash(target.partition(":")[0]),
        )

    def _target(self, name: str) -> str:
        """``module:attribute`` of `name`'s piece (loaded already)."""
        point = self.installed().get(name)
        if point is not None:
            return point.value
        if ":" in name:
            return name
        module, attribute = name, ""  # the dotted form: its longest prefix that is a module
        while module and module not in sys.modules:
            module, _, tail = module.rpartition(".")
            attribute = f"{tail}.{attribute}" if attribute else tail
        return f"{module}:{attribute}" if module else name

    def _load(self, name: str) -> T:
        point = self.installed().get(name)
        if point is not None:
            where = f"the entry point {name!r} of group {self.group} ({point.value})"
            loader: Callable[[], object] = point.load
        elif ":" in name or "." in name:
            where = f"{self.kind} {name!r}"

            def loader() -> object:
                return pkgutil.resolve_name(name)
        else:
            known = ", ".join(self.names())
            raise PluginError(
                f"unknown {self.kind} {name!r}; choose from {known}, or name one in your package "
                "as package.module:name"
            )
        try:
            loaded = loader()
        except Exception as error:  # a plugin's import may raise anything
            raise PluginError(f"{where} failed to load: {_one_line(error)}") from None
        try:
            return self._check(loaded)
        except (TypeError, ValueError) as error:
            raise PluginError(f"{where} is not a {self.kind}: {error}") from None


def check_plugins(wanted: Iterable[Plugin], registries: Mapping[str, Registry[Any]]) -> None:
    """`PluginError` naming the first of `wanted` that this process lacks or holds in another
    version or source (a job's plugins, checked by the node that runs it)."""
    for plugin in wanted:
        registry = registries.get(plugin.kind)
        if registry is None:
            raise PluginError(f"unknown kind of plugin {plugin.kind!r} ({plugin.name})")
        try:
            mine = registry.identity(plugin.name)
        except PluginError as error:
            raise PluginError(
                f"lacks the {plugin.kind} plugin {plugin.describe()}: {error}"
            ) from None
        if mine is None or mine.model_dump(exclude={"kind", "name"}) != plugin.model_dump(
            exclude={"kind", "name"}
        ):
            held = "a built-in" if mine is None else mine.describe()
            raise PluginError(
                f"holds another {plugin.kind} plugin {plugin.name}: the job's is "
                f"{plugin.describe()}, this node's {held}"
            )


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _distribution(target: str, point: EntryPoint | None) -> tuple[str, str]:
    """The distribution and version holding `target` (an entry point's own, else the one that
    installs its top-level package; ('', '') for a module that is only on the path)."""
    if point is not None and point.dist is not None:
        return point.dist.name, point.dist.version
    top = target.partition(":")[0].partition(".")[0]
    names = packages_distributions().get(top, [])
    return (names[0], version(names[0])) if names else ("", "")


@cache
def _source_hash(module: str) -> str:
    """SHA-256 over the source files of `module`'s top-level package (relative path and bytes of
    every ``.py`` file in it, in order), or of the module's own file."""
    top = importlib.import_module(module.partition(".")[0])
    digest = hashlib.sha256()
    paths = [Path(p) for p in getattr(top, "__path__", [])]
    if paths:
        files = sorted(
            (f.relative_to(root).as_posix(), f) for root in paths for f in root.rglob("*.py")
        )
    else:
        origin = Path(top.__file__ or "")
        files = [(origin.name, origin)]
    for relative, path in files:
        digest.update(relative.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()
