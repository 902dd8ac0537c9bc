"""Names a package offers but loads on first use (PEP 562), so that importing the package stays cheap."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping


def lazy_attributes(package: str, homes: Mapping[str, str]) -> Callable[[str], object]:
    """A module-level ``__getattr__`` for `package`: ``homes`` maps each lazily offered name to the module that
    defines it, imported when the name is first looked up.

    Use as ``__getattr__ = lazy_attributes(__name__, {"ground": "grounder.grounding.pipeline"})``.
    """

    def __getattr__(name: str) -> object:
        if name in homes:
            return getattr(importlib.import_module(homes[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
