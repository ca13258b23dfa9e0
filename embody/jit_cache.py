"""Load numba's cached kernels before their first call.

A compiled kernel (`@njit(cache=True)`) is loaded from numba's on-disk cache on its first call
in a process, under numba's compiler lock. A run's worker threads start their first steps at
once, so one loaded ~25 kernels (~1.5 s) while the other waited on that lock. The flow loads
them in the driver instead, while Prefect's server boots (`tasks.stages.warm`). Only entries
valid for this process are loaded (same numba version, source stamp, bytecode and CPU); a
stale or missing entry is left for the first call to compile, as before.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable
from types import ModuleType

__all__ = ["load_cached_kernels"]


def _dispatchers(modules: Iterable[ModuleType]) -> list:
    from numba.core.registry import CPUDispatcher
    seen: dict[int, object] = {}
    for module in modules:
        for obj in list(vars(module).values()):
            if isinstance(obj, CPUDispatcher) and getattr(obj, "_cache", None) is not None:
                seen.setdefault(id(obj), obj)
    return list(seen.values())


def load_cached_kernels(modules: Iterable[ModuleType] | None = None) -> int:
    """Load every cached overload of the compiled kernels in `modules` (default: the loaded
    `embody` modules); returns how many were loaded. Best effort: never compiles, never raises
    on a cache it cannot read."""
    if modules is None:
        modules = [m for name, m in list(sys.modules.items())
                   if (name == "embody" or name.startswith("embody.")) and m is not None]
    loaded = 0
    for dispatcher in _dispatchers(modules):
        try:
            cache = dispatcher._cache
            codegen = dispatcher.targetctx.codegen()
            index = cache._cache_file._load_index()
        except Exception:
            continue
        for key, data_name in index.items():
            sig = key[0]
            if sig in dispatcher.overloads:
                continue
            try:
                if cache._index_key(sig, codegen) != key:  # another CPU, or stale bytecode
                    continue
                if not os.path.isfile(os.path.join(cache._cache_file._cache_path, data_name)):
                    continue  # the index outlived its data file: compiling is the call's job
                dispatcher.compile(sig)  # a cache hit: loads and registers the overload
                loaded += 1
            except Exception:
                continue
    return loaded
