"""One registry pattern for every plug-in seam: score terms, detector families, camera-pose
sources and engine backends.

A :class:`Registry` maps a name (the value of the parameter that selects the plug-in) to an
entry. Entries come from two places: built-in modules named up front (imported on first use, so a
backend whose library is missing costs nothing until it is chosen) and :meth:`Registry.register`
(a plug-in module, or a test, adds one without editing the registry's file). An unknown name is a
``ValueError`` that lists the known ones, so a wrong parameter value says what would have worked.
"""
from __future__ import annotations

import importlib
from typing import Callable, Dict, Generic, List, Optional, TypeVar

T = TypeVar("T")

__all__ = ["Registry"]


class Registry(Generic[T]):
    """Named plug-ins of one kind.

    Args:
        kind: What the entries are, for error messages (e.g. ``"detector family"``).
        modules: Built-in entries: name -> module path. The module is imported when the name is
            first asked for; importing it must register the name (e.g. by a decorator calling
            :meth:`register`) or define ``attribute``.
        attribute: When given, the module attribute that holds the entry (e.g. ``"FAMILY"``), for
            modules that define their entry instead of registering it.
        check: Called with each registered entry; raises ``TypeError`` for a wrong kind of object.
    """

    def __init__(self, kind: str, modules: Optional[Dict[str, str]] = None, attribute: Optional[str] = None,
                 check: Optional[Callable[[object], None]] = None) -> None:
        self.kind = kind
        self.modules: Dict[str, str] = dict(modules or {})
        self.attribute = attribute
        self._check = check
        self._entries: Dict[str, T] = {}

    def register(self, name: str, entry: T, replace: bool = False) -> T:
        """Make ``entry`` selectable as ``name``; returns it (usable as a decorator's body).

        Raises:
            TypeError: the entry is not of this registry's kind (``check``).
            ValueError: an empty name, or a name already registered (unless ``replace``).
        """
        if not name:
            raise ValueError(f"a {self.kind} needs a name")
        if self._check is not None:
            self._check(entry)
        if name in self._entries and not replace and self._entries[name] is not entry:
            raise ValueError(f"{self.kind} {name!r} is already registered")
        self._entries[name] = entry
        return entry

    def unregister(self, name: str) -> None:
        """Forget a registered entry (tests that register a throwaway plug-in)."""
        self._entries.pop(name, None)

    def names(self) -> List[str]:
        """Every selectable name, built-in or registered, sorted."""
        return sorted(set(self.modules) | set(self._entries))

    def __contains__(self, name: object) -> bool:
        return name in self._entries or name in self.modules

    def get(self, name: str) -> T:
        """The entry called ``name`` (importing its built-in module on first use).

        Raises:
            ValueError: an unknown name (the message lists the known ones).
        """
        if name not in self._entries and name in self.modules:
            module = importlib.import_module(self.modules[name])
            if self.attribute is not None and name not in self._entries:
                self.register(name, getattr(module, self.attribute))
        if name not in self._entries:
            raise ValueError(f"unknown {self.kind} {name!r}; known: {', '.join(self.names()) or 'none'}")
        return self._entries[name]
