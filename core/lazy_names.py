"""A package's public names loaded on first use (PEP 562's module `__getattr__`).

The facades (`controller/api`, `controller/harness`) name what they offer without importing it:
a small command (`cell plan`, `cell --help`) must not load the build runner, the simulators or
their libraries (start-up time). Each facade keeps a table name → the module of the package that
holds it; the first read imports that module and caches the name on the package.
"""
from __future__ import annotations

import importlib
import sys
from typing import Callable, Mapping


def lazy_names(package: str, where: Mapping[str, str]) -> Callable[[str], object]:
    """The package's `__getattr__`: `where[name]` is the module (relative to `package`) holding `name`."""
    def __getattr__(name: str) -> object:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value: object = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)   # later reads find it without this hook
        return value
    return __getattr__
