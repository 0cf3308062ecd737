"""Deferred imports for the command line: a module named here is imported on its first attribute access.

`station --help`, `station records` and `station mock` never touch numpy, yet the command modules that define
`station solve`/`fk`/`map` use it at module level; importing it eagerly would make every command pay ~0.1-0.5 s
of start-up (fast start; `bench/startup.py` measures it)."""

from __future__ import annotations

import importlib
import importlib.util
import sys
from types import ModuleType


def lazy_module(name: str) -> ModuleType:
    """``name`` as a module object that imports itself on first use (``importlib.util.LazyLoader``); the real
    module if it is already imported."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    if spec is None or spec.loader is None:
        return importlib.import_module(name)  # the normal error
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module


def lazy_names(module_name: str, where: dict[str, str]):
    """A PEP 562 ``__getattr__`` for a package whose public names (``where``: name -> defining module) are
    imported on first use: registering a command must not load numpy and the emulators behind it."""

    def __getattr__(name: str):
        if name not in where:
            raise AttributeError(f"module {module_name!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(where[name]), name)
        setattr(sys.modules[module_name], name, value)
        return value

    return __getattr__


def lazy_exports(module_name: str, exports: dict[str, tuple[str, ...]]):
    """``(__all__, __getattr__, __dir__)`` for a package whose ``__init__`` lists its public names by defining module
    (``{module: (name, ...)}``), each imported on first use (:func:`lazy_names`): ``import station.robot`` costs
    no driver, numpy or kinematics."""
    where = {name: module for module, names in exports.items() for name in names}

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[module_name])) | set(where))

    return sorted(where), lazy_names(module_name, where), __dir__
