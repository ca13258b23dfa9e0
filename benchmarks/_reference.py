"""Import a reference copy of one of our modules (an older `optimize.py`, `depth.py`) from a file
under its own name, for same-process A/B benchmarks against the current code."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType


def load_reference(path: str | Path, name: str) -> ModuleType:
    """The module at `path`, imported as `name` (registered in `sys.modules` first: its
    dataclasses look their module up while they are built)."""
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
