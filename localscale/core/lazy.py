"""Lazy package exports: a package names what its modules export, and each name is imported on first use.

    _EXPORTS = {".matcher": ("Matcher", "get_matcher"), ".config": ("MatchConfig",)}
    __all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)

Importing the package then costs nothing of what its modules import (torch, pycolmap) until a name is used.
"""

from __future__ import annotations

import importlib
import sys
from typing import Callable, Optional


def lazy_exports(package: str, exports: dict, fallback: Optional[Callable] = None) -> tuple[list, Callable, Callable]:
    """``(__all__, __getattr__, __dir__)`` of ``package`` for ``exports`` (``{".module": (names...)}``).

    ``fallback(name)``: called for a name that is not exported (it returns the value or raises
    :class:`AttributeError`), e.g. for old names forwarded elsewhere."""
    where = {name: mod for mod, names in exports.items() for name in names}

    def __getattr__(name):
        mod = where.get(name)
        if mod is None:
            if fallback is not None:
                return fallback(name)
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module = importlib.import_module(mod, package)
        for exported in exports[mod]:  # every name of the module, over a submodule of the same name
            setattr(sys.modules[package], exported, getattr(module, exported))
        return getattr(module, name)

    names = sorted(where)

    def __dir__():
        return sorted(set(vars(sys.modules[package])) | set(names))

    return names, __getattr__, __dir__
