"""Unpickling of untrusted files: an opcode interpreter that builds plain data and nothing else.

`pickle.Unpickler` calls whatever its `find_class` hands back, so even an allow-list of numpy's
own callables is unsafe: `numpy.ndarray((2,), numpy.dtype('O'), buffer=...)` builds an object
array whose element pointers are the file's bytes, and `range(2_000_000_000)` or a few KB of memo
references expand to gigabytes once a reader converts them. This reader walks the opcodes itself
(`pickletools` parses each opcode's argument), recognises by name the few calls Python's and
numpy's picklers emit (arrays, numpy scalars and dtypes, py2-style bytes, sets, OrderedDict),
builds those values itself from the stream's bytes, and refuses every other name.

It builds dict, list, tuple, set, frozenset, str, bytes, bytearray, int, float, complex, bool,
None, numpy dtypes, numpy scalars and arrays of numeric or fixed-width text dtypes (bool, int,
uint, float, complex, `S`, `U`: values without pointers; never object, void or structured).

Every size is checked on the stream before anything is allocated: input bytes, stack, memo and
container counts, nesting depth, and each value's logical size (a shared reference counts each
time it appears, so a memo-reference bomb is refused before a consumer expands it). A container
is frozen once it is stored in another, which rules out cycles and keeps logical sizes exact.
"""

from __future__ import annotations

import gzip
import io
import math
import os
import pickletools
import re
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from embody.errors import InputError


class PickleRefused(ValueError):
    """A pickle this reader will not build: corrupt, over a limit, or naming a refused callable."""


@dataclass(frozen=True)
class Budget:
    """Limits on one pickle, all checked before the thing they bound is allocated."""

    #: Input size (decompressed, for gzip files).
    max_bytes: int
    #: Logical size of any value, the result included: one per scalar, array element or
    #: container, one per 8 bytes of text; a shared reference counts every time it is used.
    max_elements: int
    #: Containers nested in containers (an array counts its dimensions).
    max_depth: int = 32
    #: Largest first axis of an array of 2 or more dimensions (frames); None: no such limit.
    max_rows: int | None = None

    @property
    def max_objects(self) -> int:
        """Containers created and memo entries, each: they cost memory while reading."""
        return max(self.max_elements // 8, 1 << 12)


#: Names a pickle may refer to, and what this reader builds for each.
_NAMES: dict[tuple[str, str], str] = {
    ("numpy.core.multiarray", "_reconstruct"): "reconstruct",
    ("numpy._core.multiarray", "_reconstruct"): "reconstruct",
    ("numpy.core.multiarray", "scalar"): "scalar",
    ("numpy._core.multiarray", "scalar"): "scalar",
    ("numpy.core.numeric", "_frombuffer"): "frombuffer",
    ("numpy._core.numeric", "_frombuffer"): "frombuffer",
    ("numpy", "ndarray"): "ndarray",  # only as _reconstruct's first argument
    ("numpy", "dtype"): "dtype",
    ("collections", "OrderedDict"): "ordereddict",
    ("builtins", "set"): "set",
    ("builtins", "frozenset"): "frozenset",
    ("builtins", "complex"): "complex",
    ("builtins", "bytes"): "bytes",
    ("builtins", "bytearray"): "bytearray",
    ("_codecs", "encode"): "encode",  # protocol 0-2 store bytes as encode(text, "latin1")
}
#: Python 2 module names that protocol 0-2 pickles carry (pickle's fix_imports).
_PY2_MODULES = {"__builtin__": "builtins", "copy_reg": "copyreg"}
#: dtype specs numpy's pickler writes for plain values: bool, ints, floats, complex, text.
_DTYPE_SPEC = re.compile(r"[<>|=]?(\?|[biufcSU]\d{0,9})")
_DTYPE_KINDS = "biufcSU"
_MAX_DIMS = 32
_MUTABLE = (list, dict, set)
_TRACKED = (list, dict, set, tuple, frozenset)


@dataclass(frozen=True)
class _Name:
    """A name from GLOBAL/STACK_GLOBAL: callable through REDUCE, never stored as data."""

    kind: str
    qualname: str


class _Pending:
    """A value BUILD completes: an array made by `_reconstruct`, or a dtype (numpy pickles both
    as a call followed by BUILD). Once stored anywhere it is final; a later BUILD is refused."""

    def __init__(self, kind: str, value: Any = None) -> None:
        self.kind = kind
        self.value = value
        self.used = False


def _refuse(message: str) -> PickleRefused:
    return PickleRefused(message)


def _describe(value: Any) -> str:
    """What a stack value is, for messages."""
    if isinstance(value, _Name):
        return value.qualname
    if isinstance(value, _Pending):
        return f"numpy {value.kind} being rebuilt"
    return f"a {type(value).__name__}"


class _Reader:
    """One pass over one pickle's opcodes; `run()` returns the top of the stack at STOP."""

    def __init__(self, raw: bytes, budget: Budget) -> None:
        self.raw = raw
        self.budget = budget
        self.stack: list[Any] = []
        self.marks: list[int] = []
        self.memo: dict[int, Any] = {}
        #: id -> [object, logical size, depth, frozen] of every container built (the object is
        #: held so its id stays unique).
        self.meta: dict[int, list[Any]] = {}
        #: ids of tuples holding a `_Name`: REDUCE arguments, never data.
        self.call_args: set[int] = set()
        self.max_objects = budget.max_objects
        self.max_elements = budget.max_elements

    # values -----------------------------------------------------------------------------------

    def _track(self, obj: Any, size: int, depth: int, frozen: bool) -> Any:
        if len(self.meta) >= self.max_objects:
            raise _refuse(f"more than {self.max_objects} containers")
        self._check(size, depth)
        self.meta[id(obj)] = [obj, size, depth, frozen]
        return obj

    def _check(self, size: int, depth: int) -> None:
        if size > self.budget.max_elements:
            raise _refuse(f"a value of {size} elements exceeds the limit of "
                          f"{self.budget.max_elements} (shared references count each use)")
        if depth > self.budget.max_depth:
            raise _refuse(f"nested deeper than {self.budget.max_depth} levels")

    def _measure(self, value: Any) -> tuple[int, int]:
        """(logical size, depth) of a value already made final by `_use`."""
        if isinstance(value, _TRACKED):
            entry = self.meta.get(id(value))
            if entry is not None and entry[0] is value:
                return entry[1], entry[2]
            return 1, 1  # the empty tuple/frozenset singletons
        if isinstance(value, np.ndarray):
            return max(value.size, 1), value.ndim
        if isinstance(value, (str, bytes, bytearray)):
            return 1 + len(value) // 8, 0
        return 1, 0

    def _use(self, value: Any, *, in_call_args: bool = False) -> Any:
        """`value` as it is stored into a container or returned: pending values resolved and
        frozen, containers frozen, names refused (except inside REDUCE's argument tuple)."""
        if isinstance(value, _Pending):
            if value.value is None:
                raise _refuse("numpy _reconstruct without its array data (BUILD)")
            value.used = True
            return value.value
        if isinstance(value, _Name):
            if in_call_args:
                return value
            raise _refuse(f"{value.qualname} used as a value")
        if isinstance(value, tuple) and id(value) in self.call_args and not in_call_args:
            raise _refuse("call arguments used as a value")
        if isinstance(value, _MUTABLE):
            entry = self.meta.get(id(value))
            if entry is not None:
                entry[3] = True
        return value

    def _mutable(self, target: Any, kind: type) -> list[Any]:
        if type(target) is not kind:
            raise _refuse(f"cannot add items to {_describe(target)}")
        entry = self.meta[id(target)]
        if entry[3]:
            raise _refuse(f"a {kind.__name__} is changed after it was stored or returned")
        return entry

    def _grow(self, entry: list[Any], values: list[Any]) -> None:
        for value in values:
            size, depth = self._measure(value)
            entry[1] += size
            entry[2] = max(entry[2], depth + 1)
        self._check(entry[1], entry[2])

    # stack --------------------------------------------------------------------------------------

    def _push(self, value: Any) -> None:
        if len(self.stack) >= self.max_elements:
            raise _refuse(f"stack deeper than {self.max_elements}")
        self.stack.append(value)

    def _pop(self) -> Any:
        if not self.stack or (self.marks and len(self.stack) <= self.marks[-1]):
            raise _refuse("stack underflow")
        return self.stack.pop()

    def _top(self) -> Any:
        if not self.stack or (self.marks and len(self.stack) <= self.marks[-1]):
            raise _refuse("stack underflow")
        return self.stack[-1]

    def _pop_mark(self) -> list[Any]:
        if not self.marks:
            raise _refuse("no MARK on the stack")
        start = self.marks.pop()
        items = self.stack[start:]
        del self.stack[start:]
        return items

    def _new_list(self, items: list[Any]) -> list[Any]:
        values = [self._use(v) for v in items]
        entry = [None, 1, 1, False]
        self._grow(entry, values)
        return self._track(values, entry[1], entry[2], False)

    def _new_tuple(self, items: list[Any]) -> tuple[Any, ...]:
        values = tuple(self._use(v, in_call_args=True) for v in items)
        entry = [None, 1, 1, True]
        self._grow(entry, [v for v in values if not isinstance(v, _Name)])
        if not values:
            return ()
        out = self._track(values, entry[1], entry[2], True)
        if any(isinstance(v, _Name) or (isinstance(v, tuple) and id(v) in self.call_args)
               for v in values):
            self.call_args.add(id(out))
        return out

    def _set_items(self, target: Any, items: list[Any]) -> None:
        entry = self._mutable(target, dict)
        if len(items) % 2:
            raise _refuse("odd number of dict keys and values")
        values = [self._use(v) for v in items]
        if entry[3]:  # the dict itself was among its items
            raise _refuse("a dict is stored in itself")
        self._grow(entry, values)
        try:
            for i in range(0, len(values), 2):
                target[values[i]] = values[i + 1]
        except TypeError as exc:
            raise _refuse(f"unusable dict key: {exc}") from None

    def _add_to_set(self, target: Any, items: list[Any]) -> None:
        entry = self._mutable(target, set)
        values = [self._use(v) for v in items]
        self._grow(entry, values)
        try:
            target.update(values)
        except TypeError as exc:
            raise _refuse(f"unusable set item: {exc}") from None

    def _append(self, target: Any, items: list[Any]) -> None:
        entry = self._mutable(target, list)
        values = [self._use(v) for v in items]
        if entry[3]:
            raise _refuse("a list is stored in itself")
        self._grow(entry, values)
        target.extend(values)

    def _frozenset(self, items: list[Any]) -> frozenset[Any]:
        values = [self._use(v) for v in items]
        entry = [None, 1, 1, True]
        self._grow(entry, values)
        try:
            out = frozenset(values)
        except TypeError as exc:
            raise _refuse(f"unusable set item: {exc}") from None
        return self._track(out, entry[1], entry[2], True) if out else out

    # numpy --------------------------------------------------------------------------------------

    def _dtype(self, spec: Any) -> np.dtype:
        if not isinstance(spec, str) or not _DTYPE_SPEC.fullmatch(spec):
            raise _refuse(f"dtype {str(spec)[:40]!r} is not a plain numeric or text dtype")
        try:
            dtype = np.dtype(spec)
        except TypeError as exc:
            raise _refuse(f"dtype {spec!r}: {exc}") from None
        if dtype.kind not in _DTYPE_KINDS or dtype.hasobject or dtype.fields is not None \
                or dtype.subdtype is not None:
            raise _refuse(f"dtype {spec!r} is not a plain numeric or text dtype")
        return dtype

    def _dtype_state(self, dtype: np.dtype, state: Any) -> np.dtype:
        """numpy's dtype `__setstate__` for plain dtypes: byte order and text width."""
        if not isinstance(state, tuple) or len(state) not in (8, 9) or state[0] not in (3, 4):
            raise _refuse("unsupported dtype state")
        endian, subarray, names, fields, elsize = state[1:6]
        if subarray is not None or names is not None or fields is not None \
                or (len(state) == 9 and state[8] is not None):
            raise _refuse("structured, subarray or annotated dtypes are refused")
        if endian not in ("<", ">", "|", "=") or type(elsize) is not int:
            raise _refuse("unsupported dtype state")
        if dtype.kind in "SU" and elsize > 0:
            width = 4 if dtype.kind == "U" else 1
            if elsize % width or elsize > self.budget.max_bytes:
                raise _refuse(f"text dtype of {elsize} bytes")
            dtype = np.dtype(f"{dtype.kind}{elsize // width}")
        elif elsize not in (-1, dtype.itemsize):
            raise _refuse(f"dtype {dtype} with item size {elsize}")
        if endian in "<>" and dtype.itemsize > 1 and dtype.kind != "S":
            dtype = dtype.newbyteorder(endian)
        return dtype

    def _shape(self, shape: Any) -> tuple[int, ...]:
        limit = self.budget.max_elements
        if not isinstance(shape, tuple) or len(shape) > _MAX_DIMS \
                or not all(type(n) is int and 0 <= n <= limit for n in shape):
            raise _refuse(f"array shape {str(shape)[:60]} is not a tuple of sizes")
        count = math.prod(shape)
        self._check(count, len(shape))
        rows = self.budget.max_rows
        if rows is not None and len(shape) >= 2 and shape[0] > rows:
            raise _refuse(f"array of {shape[0]} frames exceeds io.max_frames={rows}")
        return shape

    def _array(self, raw: Any, dtype: Any, shape: Any, order: str) -> np.ndarray:
        if not isinstance(dtype, np.dtype):
            raise _refuse("array without a dtype")
        if dtype.itemsize == 0:
            raise _refuse("array of zero-width items")
        shape = self._shape(shape)
        if isinstance(raw, str):  # Python 2 pickles: raw bytes read as latin-1 text
            try:
                raw = raw.encode("latin-1")
            except UnicodeEncodeError:
                raise _refuse("array data is not bytes") from None
        if not isinstance(raw, (bytes, bytearray)):
            raise _refuse(f"array data is a {type(raw).__name__} (object arrays are refused)")
        count = math.prod(shape)
        if len(raw) != count * dtype.itemsize:
            raise _refuse(f"array data of {len(raw)} bytes for shape {shape} of {dtype} "
                          f"({count * dtype.itemsize} bytes)")
        if count == 0:
            return np.zeros(shape, dtype)
        return np.frombuffer(raw, dtype=dtype, count=count).reshape(shape, order=order).copy(order="K")

    def _scalar(self, dtype: Any, raw: Any) -> Any:
        if not isinstance(dtype, np.dtype) or dtype.itemsize == 0:
            raise _refuse("numpy scalar without a usable dtype")
        if isinstance(raw, str):
            try:
                raw = raw.encode("latin-1")
            except UnicodeEncodeError:
                raise _refuse("numpy scalar data is not bytes") from None
        if not isinstance(raw, (bytes, bytearray)) or len(raw) != dtype.itemsize:
            raise _refuse(f"numpy scalar of {dtype} needs {dtype.itemsize} bytes")
        return np.frombuffer(raw, dtype=dtype, count=1)[0]

    # calls --------------------------------------------------------------------------------------

    def _call(self, name: Any, args: Any) -> Any:
        if not isinstance(name, _Name):
            raise _refuse(f"calling {_describe(name)}")
        if not isinstance(args, tuple):
            raise _refuse(f"{name.qualname} called with {type(args).__name__} arguments")
        kind, n = name.kind, len(args)
        if kind == "reconstruct":
            if n != 3 or not (isinstance(args[0], _Name) and args[0].kind == "ndarray"):
                raise _refuse(f"{name.qualname} of anything but numpy.ndarray")
            return _Pending("array")
        if any(isinstance(a, _Name) or (isinstance(a, tuple) and id(a) in self.call_args)
               for a in args):
            raise _refuse(f"{name.qualname} called with a name as argument")
        if kind == "dtype" and 1 <= n <= 3 and all(type(a) in (bool, int) for a in args[1:]):
            return _Pending("dtype", self._dtype(args[0]))
        if kind == "scalar" and n == 2:
            return self._scalar(args[0], args[1])
        if kind == "frombuffer" and n == 4 and args[3] in ("C", "F"):
            return self._array(args[0], args[1], args[2], args[3])
        if kind == "encode" and n == 2 and isinstance(args[0], str) \
                and args[1] in ("latin1", "latin-1"):
            try:
                return args[0].encode("latin-1")
            except UnicodeEncodeError:
                raise _refuse("_codecs.encode of text outside latin-1") from None
        if kind == "bytes" and n == 0:
            return b""
        if kind == "bytearray":
            if n == 0:
                return bytearray()
            if n == 1 and isinstance(args[0], (bytes, bytearray)):
                return bytearray(args[0])
            if n == 2 and isinstance(args[0], str) and args[1] in ("latin1", "latin-1"):
                try:
                    return bytearray(args[0].encode("latin-1"))
                except UnicodeEncodeError:
                    raise _refuse("bytearray of text outside latin-1") from None
        if kind == "complex" and 1 <= n <= 2 and all(type(a) in (int, float) for a in args):
            try:
                return complex(*args)
            except OverflowError:
                raise _refuse("complex number out of range") from None
        if kind in ("set", "frozenset", "ordereddict") and n <= 1:
            items = args[0] if n else []
            if not isinstance(items, (list, tuple)):
                raise _refuse(f"{name.qualname} of a {type(items).__name__}")
            if kind == "frozenset":
                return self._frozenset(list(items))
            if kind == "set":
                out = self._track(set(), 1, 1, False)
                self._add_to_set(out, list(items))
                return out
            out = self._track({}, 1, 1, False)
            flat: list[Any] = []
            for pair in items:
                if not isinstance(pair, (list, tuple)) or len(pair) != 2:
                    raise _refuse("OrderedDict items are not (key, value) pairs")
                flat.extend(pair)
            self._set_items(out, flat)
            return out
        raise _refuse(f"unsupported arguments to {name.qualname}")

    def _build(self, target: Any, state: Any) -> None:
        if not isinstance(target, _Pending) or target.used:
            raise _refuse(f"BUILD on {_describe(target)}")
        if target.kind == "dtype":
            target.value = self._dtype_state(target.value, state)
            return
        if target.value is not None:
            raise _refuse("BUILD twice on one array")
        if not isinstance(state, tuple) or len(state) not in (4, 5):
            raise _refuse("unsupported array state")
        if len(state) == 5:
            if state[0] != 1:
                raise _refuse(f"unsupported array state version {state[0]!r}")
            state = state[1:]
        shape, dtype, fortran, raw = state
        if type(fortran) not in (bool, int):
            raise _refuse("unsupported array state")
        array = self._array(raw, dtype, shape, "F" if fortran else "C")
        # numpy's __setstate__ hands back non-native data in native byte order
        target.value = array if array.dtype.isnative else array.astype(array.dtype.newbyteorder("="))

    def _global(self, module: str, name: str) -> _Name:
        module = _PY2_MODULES.get(module, module)
        kind = _NAMES.get((module, name))
        if kind is None:
            raise _refuse(f"refusing to unpickle {module}.{name}"[:200])
        return _Name(kind, f"{module}.{name}")

    # opcodes ------------------------------------------------------------------------------------

    def _memo_put(self, key: int) -> None:
        if key not in self.memo and len(self.memo) >= self.max_objects:
            raise _refuse(f"more than {self.max_objects} memo entries")
        self.memo[key] = self._top()

    def _op_push(self, arg: Any) -> None:
        self._push(arg)

    def _op_const(self, value: Any) -> Any:
        return lambda _: self._push(value)

    def _op_mark(self, _: Any) -> None:
        if len(self.marks) >= self.budget.max_elements:
            raise _refuse("too many MARKs")
        self.marks.append(len(self.stack))

    def _op_tuple_n(self, count: int) -> Any:
        def op(_: Any) -> None:
            items = [self._pop() for _ in range(count)][::-1]
            self._push(self._new_tuple(items))
        return op

    def _op_dict(self, _: Any) -> None:
        items = self._pop_mark()
        out = self._track({}, 1, 1, False)
        self._set_items(out, items)
        self._push(out)

    def _op_append(self, _: Any) -> None:
        value = self._pop()
        self._append(self._top(), [value])

    def _op_setitem(self, _: Any) -> None:
        value = self._pop()
        key = self._pop()
        self._set_items(self._top(), [key, value])

    def _op_pop(self, _: Any) -> None:
        if self.stack and not (self.marks and len(self.stack) <= self.marks[-1]):
            self.stack.pop()
        else:
            self._pop_mark()

    def _op_get(self, key: int) -> None:
        if key not in self.memo:
            raise _refuse(f"memo key {key} was never stored")
        self._push(self.memo[key])

    def _op_global(self, arg: str) -> None:
        module, _, attr = arg.partition(" ")
        self._push(self._global(module, attr))

    def _op_stack_global(self, _: Any) -> None:
        attr = self._pop()
        module = self._pop()
        if not isinstance(module, str) or not isinstance(attr, str):
            raise _refuse("STACK_GLOBAL of non-text names")
        self._push(self._global(module, attr))

    def _op_reduce(self, _: Any) -> None:
        args = self._pop()
        self._push(self._call(self._pop(), args))

    def _op_build(self, _: Any) -> None:
        state = self._use(self._pop())
        self._build(self._top(), state)

    def _op_proto(self, arg: int) -> None:
        if not 0 <= arg <= 5:
            raise _refuse(f"unsupported pickle protocol {arg}")

    def _op_readonly_buffer(self, _: Any) -> None:
        if not isinstance(self._top(), (bytes, bytearray)):
            raise _refuse("READONLY_BUFFER on a non-buffer")

    def _ops(self) -> dict[str, Any]:
        """Opcode name -> handler of its parsed argument. Opcodes missing here (INST, OBJ,
        NEWOBJ, NEWOBJ_EX, PERSID, BINPERSID, EXT1/2/4, NEXT_BUFFER) build objects or need data
        from outside the file, and are refused."""
        ops: dict[str, Any] = {name: self._op_push for name in _PUSH_ARG}
        ops.update({
            "NONE": self._op_const(None), "NEWTRUE": self._op_const(True),
            "NEWFALSE": self._op_const(False), "EMPTY_TUPLE": self._op_const(()),
            "EMPTY_LIST": lambda _: self._push(self._track([], 1, 1, False)),
            "EMPTY_DICT": lambda _: self._push(self._track({}, 1, 1, False)),
            "EMPTY_SET": lambda _: self._push(self._track(set(), 1, 1, False)),
            "MARK": self._op_mark,
            "LIST": lambda _: self._push(self._new_list(self._pop_mark())),
            "TUPLE": lambda _: self._push(self._new_tuple(self._pop_mark())),
            "TUPLE1": self._op_tuple_n(1), "TUPLE2": self._op_tuple_n(2),
            "TUPLE3": self._op_tuple_n(3),
            "DICT": self._op_dict,
            "FROZENSET": lambda _: self._push(self._frozenset(self._pop_mark())),
            "APPEND": self._op_append,
            "APPENDS": lambda _: self._append(*self._target_and_items()),
            "SETITEM": self._op_setitem,
            "SETITEMS": lambda _: self._set_items(*self._target_and_items()),
            "ADDITEMS": lambda _: self._add_to_set(*self._target_and_items()),
            "POP": self._op_pop, "POP_MARK": lambda _: self._pop_mark(),
            "DUP": lambda _: self._push(self._top()),
            "PUT": self._memo_put, "BINPUT": self._memo_put, "LONG_BINPUT": self._memo_put,
            "MEMOIZE": lambda _: self._memo_put(len(self.memo)),
            "GET": self._op_get, "BINGET": self._op_get, "LONG_BINGET": self._op_get,
            "GLOBAL": self._op_global, "STACK_GLOBAL": self._op_stack_global,
            "REDUCE": self._op_reduce, "BUILD": self._op_build,
            "PROTO": self._op_proto, "FRAME": lambda _: None,
            "READONLY_BUFFER": self._op_readonly_buffer,
        })
        return ops

    def _target_and_items(self) -> tuple[Any, list[Any]]:
        items = self._pop_mark()
        return self._top(), items

    def run(self) -> Any:
        ops = self._ops()
        for op, arg, _ in pickletools.genops(self.raw):
            if op.name == "STOP":
                result = self._use(self._pop())
                self._check(*self._measure(result))
                return result
            handler = ops.get(op.name)
            if handler is None:
                raise _refuse(f"opcode {op.name} is refused (it builds objects or needs outside data)")
            handler(arg)
        raise _refuse("pickle ends before STOP")


#: Opcodes whose parsed argument is the value pushed.
_PUSH_ARG = frozenset({
    "INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4", "FLOAT", "BINFLOAT",
    "STRING", "BINSTRING", "SHORT_BINSTRING", "BINBYTES", "SHORT_BINBYTES", "BINBYTES8",
    "BYTEARRAY8",  # pickletools reads it as a bytearray
    "UNICODE", "BINUNICODE", "SHORT_BINUNICODE", "BINUNICODE8"})


def _brief(exc: BaseException) -> str:
    """An exception as one short line: errors name file and field in a single line."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def loads(raw: bytes, budget: Budget) -> Any:
    """The plain data a pickle holds; anything else, or anything over `budget`, is refused."""
    if len(raw) > budget.max_bytes:
        raise PickleRefused(f"{len(raw)} bytes exceeds the limit of {budget.max_bytes}")
    try:
        return _Reader(raw, budget).run()
    except PickleRefused as exc:
        raise PickleRefused(_brief(exc)) from None
    except MemoryError:
        raise PickleRefused("out of memory while reading") from None
    except RecursionError:
        raise PickleRefused("nested too deeply") from None
    except Exception as exc:  # pickletools raises several types on corrupt input
        raise PickleRefused(f"corrupt pickle: {type(exc).__name__}: {_brief(exc)}") from None


_CHUNK = 1 << 20


def _read_capped(fh: Any, limit: int) -> bytes:
    """At most `limit + 1` bytes of `fh`, read in chunks (one `read(limit)` would allocate
    `limit` bytes up front, whatever the stream holds)."""
    chunks: list[bytes] = []
    size = 0
    while size <= limit:
        chunk = fh.read(min(_CHUNK, limit + 1 - size))
        if not chunk:
            break
        chunks.append(chunk)
        size += len(chunk)
    return chunks[0] if len(chunks) == 1 else b"".join(chunks)


def _gunzip(raw: bytes, limit: int) -> bytes:
    try:
        with gzip.GzipFile(fileobj=io.BytesIO(raw)) as fh:
            out = _read_capped(fh, limit)
    except (OSError, EOFError, zlib.error) as exc:
        raise PickleRefused(f"corrupt gzip data: {_brief(exc)}") from None
    if len(out) > limit:
        raise PickleRefused(f"decompresses to more than {limit} bytes")
    return out


def read(path: Path, budget: Budget, *, gz: bool = False) -> Any:
    """`loads` of a file (gzip when `gz` or when it starts with gzip's magic); every failure is
    an InputError naming the file, in one line."""
    try:
        with path.open("rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            raw = fh.read(min(size, budget.max_bytes) + 1)
    except OSError as exc:
        raise InputError(path, None, f"cannot read file: {exc.strerror or exc}") from None
    try:
        if len(raw) > budget.max_bytes:
            raise PickleRefused(f"file is larger than the limit of {budget.max_bytes} bytes")
        if gz or raw[:2] == b"\x1f\x8b":
            raw = _gunzip(raw, budget.max_bytes)
        return loads(raw, budget)
    except PickleRefused as exc:
        raise InputError(path, None, f"unreadable pickle: {exc}") from None
