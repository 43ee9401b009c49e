"""One registry shape for everything shiftkit finds by name: stages, env families, experts,
importers, trainers, executors and commands.

A `Registry` holds the named things of one kind. The module that defines a thing registers it
(`register`, or `named(name)` as a decorator); code elsewhere asks by name (`get`, one line naming
the known ones when the name is unknown), lists (`names`, `items`) and never keeps its own list.
What a registry holds is found, not listed: its discoverers (`import_modules` of a package's folder,
`import_entry_points` of a plugin group) run once, on the first question asked of it, so importing
a registry loads nothing else.

The class lives here, in `shiftkit.envs`, because it is the lowest layer that needs one (env
families and their experts) and envs may import nothing else of shiftkit; every layer above imports
it from here. This module imports nothing beyond the standard library (docs/architecture.md).
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable, Iterable, Iterator
from importlib import metadata


class Registry[T]:
    """The things of one kind (`kind`, as error messages name it) by name. `error`: the exception
    type of an unknown name (a layer's user-error type, e.g. `ConfigError`); `discover`: callables
    that import the modules which register the things, run once before the first lookup (more can
    be added with `discover_with`)."""

    def __init__(
        self, kind: str, *, error: type[Exception] = LookupError, discover: Iterable[Callable[[], None]] = ()
    ) -> None:
        self.kind = kind
        self._error = error
        self._items: dict[str, T] = {}
        self._discoverers = list(discover)
        self._discovered = False

    def register(self, item: T, name: str | None = None) -> T:
        """Add `item` under `name` (default: its `name` attribute); registering the same item again is
        a no-op, another item under a taken name a TypeError. Returns `item` (usable as a decorator)."""
        name = name if name is not None else item.name  # type: ignore[attr-defined]
        known = self._items.get(name)
        if known is not None and known is not item and known != item:
            raise TypeError(f"{self.kind} {name!r} is registered twice ({_label(known)}, {_label(item)})")
        self._items[name] = item
        return item

    def named(self, name: str) -> Callable[[T], T]:
        """A decorator registering what it decorates under `name`."""
        return lambda item: self.register(item, name)

    def discover_with(self, discoverer: Callable[[], None]) -> None:
        """Add a discoverer; it runs before the next lookup (at once if the registry was asked before)."""
        self._discoverers.append(discoverer)
        if self._discovered:
            discoverer()

    def _found(self) -> dict[str, T]:
        if not self._discovered:
            self._discovered = True  # first, so that a discovered module asking the registry does not recurse
            try:
                for discoverer in self._discoverers:
                    discoverer()
            except BaseException:
                self._discovered = False  # asked again, it tries again (and fails with the same message)
                raise
        return self._items

    def get(self, name: str) -> T:
        """The thing registered as `name`; `error` with one line naming the known ones otherwise."""
        items = self._found()
        if name not in items:
            raise self._error(f"unknown {self.kind} {name!r} (known: {', '.join(sorted(items)) or 'none'})")
        return items[name]

    def names(self) -> list[str]:
        """Every registered name, sorted."""
        return sorted(self._found())

    def items(self) -> list[tuple[str, T]]:
        """Every (name, registered thing), sorted by name."""
        items = self._found()
        return [(name, items[name]) for name in sorted(items)]

    def __contains__(self, name: object) -> bool:
        return name in self._found()

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())


def _label(item: object) -> str:
    return getattr(item, "__qualname__", None) or type(item).__name__


def import_modules(package: str, path: Iterable[str], packages_only: bool = False) -> None:
    """Import every module (with `packages_only`, every subpackage) found on `path` (a package's
    `__path__`) as `package.<name>`: how a package loads the things its modules register without
    listing them."""
    for module in pkgutil.iter_modules(list(path)):
        if module.ispkg or not packages_only:
            importlib.import_module(f"{package}.{module.name}")


def import_entry_points(group: str) -> None:
    """Import the module of every installed entry point of `group`: how a registry finds what an
    application (or another installed package) registers, without naming it."""
    for entry_point in metadata.entry_points(group=group):
        entry_point.load()


# The entry-point group through which an application plugs its stages and importers into the
# registries of the layers below it (shiftkit's own: `shiftkit.app.plugins`, pyproject.toml).
PLUGINS = "shiftkit.plugins"


def import_plugins() -> None:
    """Import every installed `shiftkit.plugins` entry point (the discoverer of the stage and importer
    registries)."""
    import_entry_points(PLUGINS)
