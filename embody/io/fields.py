"""Reading raw fields out of files, with errors that name the file and the field."""

from __future__ import annotations

import reprlib
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from embody.errors import InputError
from embody.io import safe_pickle
from embody.io.limits import pickle_budget
from embody.io.safe_pickle import Budget


def _brief(exc: BaseException) -> str:
    """An exception as one line: errors name file and field in a single line."""
    return " ".join(str(exc).split()) or type(exc).__name__


def read_pickle(path: Path, *, gz: bool = False, budget: Budget | None = None) -> Any:
    """A (optionally gzip) pickle of plain data and numeric arrays, read by `safe_pickle` within
    `budget` (default: what `io.max_frames` allows); any failure is an InputError."""
    return safe_pickle.read(path, budget or pickle_budget(), gz=gz)


def _npy_header(fh: Any) -> tuple[tuple[int, ...], np.dtype]:
    """(shape, dtype) from an .npy stream's header; reads only the header bytes."""
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version in ((2, 0), (3, 0)):  # 3.0 differs only in allowing utf-8 field names
        shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
    else:
        raise ValueError(f"unsupported .npy format version {version}")
    return tuple(int(n) for n in shape), dtype


def npz_shapes(path: Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Each npz member's (shape, dtype) from its header, decompressing only the header."""
    out = {}
    with zipfile.ZipFile(path) as zf:
        members = zf.infolist()
        if len(members) > 1000:
            raise ValueError(f"{len(members)} members")
        for info in members:
            if not info.filename.endswith(".npy"):  # numpy hands these back as raw bytes
                out[info.filename] = ((info.file_size,), np.dtype(np.uint8))
                continue
            with zf.open(info) as fh:
                out[info.filename[:-4]] = _npy_header(fh)
    return out


def read_npz(path: Path, limits: Any = None) -> dict[str, np.ndarray]:
    """All arrays of an npz (pickled objects refused); truncation is an InputError.

    Array sizes are checked against `limits` (`io` config) from the headers first, so a
    small file of zeros cannot decompress into gigabytes.
    """
    from embody.io.limits import check_array_header
    try:
        for key, (shape, _) in npz_shapes(path).items():
            check_array_header(path, key, shape, limits)
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except OSError as exc:
        raise InputError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    except (zipfile.BadZipFile, ValueError, EOFError, KeyError, zlib.error, SyntaxError,
            TypeError, NotImplementedError) as exc:
        raise InputError(path, None, f"truncated or corrupt npz: {_brief(exc)}") from None


def read_npy(path: Path, limits: Any = None) -> np.ndarray:
    from embody.io.limits import check_array_header
    try:
        with path.open("rb") as fh:
            shape, _ = _npy_header(fh)
        check_array_header(path, "poses", shape, limits)
        return np.load(path, allow_pickle=False)
    except OSError as exc:
        raise InputError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    except (ValueError, EOFError, SyntaxError, TypeError, NotImplementedError) as exc:
        raise InputError(path, None, f"truncated or corrupt npy: {_brief(exc)}") from None


#: What converting a field to an array raises on ragged, deeply nested or oversized values.
_ARRAY_ERRORS = (TypeError, ValueError, OverflowError, RecursionError, MemoryError)


def _array(data: dict[str, Any], key: str, path: Path | str) -> np.ndarray:
    """`data[key]` as an array; values that do not form one are an InputError naming the field."""
    try:
        return np.asarray(data[key])
    except _ARRAY_ERRORS as exc:
        raise InputError(path, key, f"not a numeric array (type {type(data[key]).__name__}: "
                                    f"{type(exc).__name__}: {_brief(exc)[:160]})") from None


def _refuse_kind(data: dict[str, Any], key: str, path: Path) -> None:
    """Bool and complex values convert to float silently (True → 1.0, imaginary part dropped)."""
    kind = _array(data, key, path).dtype.kind
    if kind in "bc":
        name = "bool" if kind == "b" else "complex"
        raise InputError(path, key, f"{name} values are refused (expected real numbers)")


def field(data: dict[str, Any], key: str, path: Path, *, width: int | None = None,
          rows: int | None = None) -> np.ndarray:
    """`data[key]` as a finite float array; `width` checks the last axis, `rows` the first."""
    if key not in data:
        raise InputError(path, key, "missing")
    _refuse_kind(data, key, path)
    try:
        arr = np.asarray(data[key], dtype=np.float64)
    except _ARRAY_ERRORS:
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
            _refuse_kind(data, key, path)
            try:
                value = float(_array(data, key, path).reshape(-1)[0])
            except (TypeError, ValueError, IndexError):
                raise InputError(path, key, f"not a number: {reprlib.repr(data[key])}") from None
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


def text(data: dict[str, Any], key: str, default: str, path: Path | None = None) -> str:
    """A string field (numpy 0-d string arrays included); non-text values are an InputError."""
    if key not in data:
        return default
    arr = _array(data, key, path or "<data>").reshape(-1)
    if not arr.size:
        return default
    if arr.dtype.kind not in "USO":
        raise InputError(path or "<data>", key, f"expected text, got {arr.dtype} values")
    item = arr[0].item() if hasattr(arr[0], "item") else arr[0]
    if isinstance(item, bytes):
        try:
            return item.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(path or "<data>", key, "not UTF-8 text") from None
    if not isinstance(item, str):
        raise InputError(path or "<data>", key, f"expected text, got {type(item).__name__}")
    return item
