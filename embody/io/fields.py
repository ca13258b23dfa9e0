"""Reading raw fields out of files, with errors that name the file and the field."""

from __future__ import annotations

import codecs
import collections
import gzip
import importlib
import io
import pickle
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from embody.errors import InputError


def _numpy_attr(name: str) -> Any:
    """`name` from numpy's core modules, whichever layout this numpy has (1.x `numpy.core`,
    2.x `numpy._core`), so pickles written by either load under either."""
    for module in ("numpy._core.multiarray", "numpy._core.numeric", "numpy.core.multiarray",
                   "numpy.core.numeric"):
        try:
            obj = getattr(importlib.import_module(module), name, None)
        except ImportError:
            continue
        if obj is not None:
            return obj
    raise pickle.UnpicklingError(f"this numpy has no {name}")


class _NumpyUnpickler(pickle.Unpickler):
    """Unpickles plain containers and numpy arrays only: field pickles need nothing else,
    and refusing other classes keeps a hostile pickle from running code.

    Only exact (module, name) pairs are resolved, from a fixed table: a module prefix would let
    a dotted name (`numpy.lib._datasource` + `os.system`) reach any attribute of any module.
    """

    _CORE_NAMES = {"numpy.core.multiarray": ("_reconstruct", "scalar"),
                   "numpy._core.multiarray": ("_reconstruct", "scalar"),
                   "numpy.core.numeric": ("_frombuffer",),
                   "numpy._core.numeric": ("_frombuffer",)}
    _ALLOWED: dict[tuple[str, str], Any] = {
        ("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype,
        ("collections", "OrderedDict"): collections.OrderedDict,
        ("builtins", "set"): set, ("builtins", "frozenset"): frozenset,
        ("builtins", "complex"): complex, ("builtins", "slice"): slice,
        ("builtins", "range"): range,
        # protocol 0-2 pickles store bytes as _codecs.encode(text, "latin1")
        ("_codecs", "encode"): codecs.encode,
    }

    def find_class(self, module: str, name: str) -> Any:
        if "." not in name:
            if (module, name) in self._ALLOWED:
                return self._ALLOWED[(module, name)]
            if name in self._CORE_NAMES.get(module, ()):
                return _numpy_attr(name)
        raise pickle.UnpicklingError(f"refusing to unpickle {module}.{name}")


def _brief(exc: BaseException) -> str:
    """An exception as one line: errors name file and field in a single line."""
    return " ".join(str(exc).split()) or type(exc).__name__


def read_pickle(path: Path, *, gz: bool = False) -> Any:
    """Load a (optionally gzip) pickle of dicts/lists/arrays; any failure is an InputError."""
    try:
        raw = path.read_bytes()
        if gz or raw[:2] == b"\x1f\x8b":
            raw = gzip.decompress(raw)
        return _NumpyUnpickler(io.BytesIO(raw), encoding="latin1").load()
    except OSError as exc:
        raise InputError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    except Exception as exc:  # pickle raises many types on corrupt input
        raise InputError(path, None, f"unreadable pickle: {type(exc).__name__}: {_brief(exc)}") from None


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """All arrays of an npz (pickled objects refused); truncation is an InputError."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except OSError as exc:
        raise InputError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    except (zipfile.BadZipFile, ValueError, EOFError, KeyError, zlib.error) as exc:
        raise InputError(path, None, f"truncated or corrupt npz: {_brief(exc)}") from None


def read_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except OSError as exc:
        raise InputError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    except (ValueError, EOFError) as exc:
        raise InputError(path, None, f"truncated or corrupt npy: {_brief(exc)}") from None


def field(data: dict[str, Any], key: str, path: Path, *, width: int | None = None,
          rows: int | None = None) -> np.ndarray:
    """`data[key]` as a finite float array; `width` checks the last axis, `rows` the first."""
    if key not in data:
        raise InputError(path, key, "missing")
    try:
        arr = np.asarray(data[key], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, key, f"not numeric (type {type(data[key]).__name__})") from None
    if width is not None and (arr.ndim != 2 or arr.shape[1] != width):
        raise InputError(path, key, f"expected shape (T, {width}), got {arr.shape}")
    if rows is not None and arr.shape[0] != rows:
        raise InputError(path, key, f"expected {rows} rows, got {arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        raise InputError(path, key, "contains non-finite values (NaN or inf)")
    return arr


def scalar(data: dict[str, Any], keys: tuple[str, ...], path: Path, default: float) -> float:
    """The first present of `keys` as a positive finite float (frame rates), else `default`."""
    for key in keys:
        if key in data:
            try:
                value = float(np.asarray(data[key]).reshape(-1)[0])
            except (TypeError, ValueError, IndexError):
                raise InputError(path, key, f"not a number: {data[key]!r}") from None
            if not np.isfinite(value) or value <= 0:
                raise InputError(path, key, f"must be > 0, got {value}")
            return value
    return default


def betas10(data: dict[str, Any], key: str, path: Path) -> np.ndarray:
    """Shape coefficients: the first 10 (AMASS ships 16), mean over frames if per-frame."""
    if key not in data:
        return np.zeros(10, np.float32)
    arr = field(data, key, path)
    if arr.ndim == 2:
        arr = arr.mean(axis=0)
    arr = arr.reshape(-1)
    if arr.shape[0] < 10:
        raise InputError(path, key, f"expected at least 10 values, got {arr.shape[0]}")
    return arr[:10].astype(np.float32)


def text(data: dict[str, Any], key: str, default: str) -> str:
    if key not in data:
        return default
    arr = np.asarray(data[key]).reshape(-1)
    if not arr.size:
        return default
    item = arr[0].item() if hasattr(arr[0], "item") else arr[0]
    return item.decode() if isinstance(item, bytes) else str(item)
