"""The one registry from method names to adapters, imported lazily ("module:Class" strings).

Adding a method is one line here; its heavy imports (torch, open3d, ...) load only when it is used.
"""
from __future__ import annotations

import difflib
import importlib

from selfseg.baselines.base import Method

METHODS: dict[str, str] = {
}


class UnknownMethodError(KeyError):
    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def method_names() -> list[str]:
    return sorted(METHODS)


def get_method_class(name: str) -> type[Method]:
    """Resolve a registered name to its adapter class; unknown names get a did-you-mean error."""
    try:
        target = METHODS[name]
    except KeyError:
        close = difflib.get_close_matches(name, METHODS, n=3)
        hint = f" Did you mean {', '.join(repr(c) for c in close)}?" if close else ""
        raise UnknownMethodError(f"unknown method {name!r}.{hint} Registered: {', '.join(method_names())}") from None
    module, _, cls = target.partition(":")
    return getattr(importlib.import_module(module), cls)
