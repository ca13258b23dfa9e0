"""The pickle reader builds plain data only, within bounds checked on the stream: hostile files
(an object array over the file's bytes, `range` and memo-reference bombs, deep nesting, ragged
fields) are refused in one line, exit 2 from the CLI, while real pickles (numpy 1.x and 2.x
layouts, protocols 0-5, Python 2 style) load with the values `pickle` itself reads.

Anything that could crash the interpreter (a plain unpickler on the object-array file, or the CLI
if the reader regressed) runs in a subprocess, so a segfault fails a test instead of pytest."""

from __future__ import annotations

import collections
import gzip
import pickle
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from embody.cli import main
from embody.config.io import IOConfig
from embody.errors import InputError
from embody.export.formats import read_gmr
from embody.io import load, load_dataset
from embody.io.fields import read_pickle
from embody.io.limits import pickle_budget
from embody.io.safe_pickle import Budget, PickleRefused, loads

ROOT = Path(__file__).resolve().parents[1]
BUDGET = Budget(max_bytes=1 << 24, max_elements=1 << 20)
T = 6


class _Call:
    """Pickles as the call `fn(*args)`: how a hostile file names a callable of its choice."""

    def __init__(self, fn, *args) -> None:
        self.fn, self.args = fn, args

    def __reduce__(self):
        return self.fn, self.args


def _object_array() -> _Call:
    """`ndarray((2,), dtype('O'), buffer=b'A'*16)`: two object pointers made of the file's bytes."""
    return _Call(np.ndarray, (2,), np.dtype("O"), b"A" * 16)


def _frame() -> dict:
    return {"smplx_root_pose": np.zeros(3, np.float32), "smplx_body_pose": np.zeros(63, np.float32),
            "smplx_lhand_pose": np.zeros(45), "smplx_rhand_pose": np.zeros(45),
            "smplx_jaw_pose": np.zeros(3), "smplx_shape": np.zeros(10), "cam_trans": np.zeros(3)}


def _cli(*argv: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """The real CLI in a child process: a crash there is an exit status here."""
    code = "import sys; from embody.cli import main; sys.exit(main(sys.argv[1:]))"
    env = {**__import__("os").environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=ROOT)


# the object array over the file's bytes ---------------------------------------------------------

def test_object_array_pickle_crashes_an_allow_list_unpickler(tmp_path):
    """What `numpy.ndarray` + `numpy.dtype` on an allow-list do with this file (the reader's old
    design): the first element read dereferences 0x4141414141414141 and the process dies."""
    path = tmp_path / "clip.pkl"
    path.write_bytes(pickle.dumps({"smplx": _object_array()}, protocol=4))
    script = textwrap.dedent(f"""
        import pickle, numpy as np
        class Unpickler(pickle.Unpickler):
            def find_class(self, module, name):
                return {{("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}}[(module, name)]
        data = Unpickler(open({str(path)!r}, "rb")).load()
        print(repr(data["smplx"][0]))
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=120)
    assert proc.returncode < 0, proc  # killed by a signal (SIGSEGV)


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_object_array_pickle_is_refused_by_the_reader(tmp_path, protocol):
    raw = pickle.dumps({"smplx": _object_array()}, protocol=protocol)
    with pytest.raises(PickleRefused, match="dtype 'O8' is not a plain numeric"):
        loads(raw, BUDGET)
    path = tmp_path / "motion.pkl"
    path.write_bytes(raw)
    with pytest.raises(InputError, match="unreadable pickle"):
        read_pickle(path)
    with pytest.raises(InputError, match="unreadable pickle"):
        read_gmr(path)


@pytest.mark.parametrize("spec", [b"O8", b"V8", b"M8"])
def test_reconstruct_with_a_non_numeric_dtype_is_refused(spec):
    """The array path numpy itself uses (`_reconstruct` + BUILD), its dtype made object, void
    (structured) or datetime: 16 bytes of data that must not become pointers or records."""
    raw = pickle.dumps(np.array([1.5, 2.5]), protocol=2)
    assert raw.count(b"X\x02\x00\x00\x00f8") == 1
    raw = raw.replace(b"X\x02\x00\x00\x00f8", b"X\x02\x00\x00\x00" + spec)
    with pytest.raises(PickleRefused, match="is not a plain numeric or text dtype"):
        loads(raw, BUDGET)


def test_structured_dtype_state_is_refused():
    raw = pickle.dumps(np.dtype([("a", "f8"), ("b", "i4")]), protocol=2)
    with pytest.raises(PickleRefused, match="dtype"):
        loads(raw, BUDGET)


def test_object_array_signavatars_file_is_one_line_exit_2_from_inspect(tmp_path):
    path = tmp_path / "clip.pkl"
    path.write_bytes(pickle.dumps({"smplx": _object_array()}, protocol=4))
    proc = _cli("inspect", str(path))
    assert proc.returncode == 2, proc
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
    assert str(path) in proc.stderr and "dtype 'O8' is not a plain numeric" in proc.stderr


def test_soke_split_that_fails_ends_run_in_one_line_exit_2(tmp_path):
    """`embody run` lists a SOKE root's split before anything starts: a hostile split file is
    one line and exit 2, no run folder."""
    (tmp_path / "poses" / "s1").mkdir(parents=True)
    split = [{"name": "s1", "text": "hi", "len": _object_array()}]
    (tmp_path / "csl_clean.train").write_bytes(gzip.compress(pickle.dumps(split, protocol=4)))
    store = tmp_path / "store"
    proc = _cli("run", str(tmp_path), "--split", "train", "--store", str(store))
    assert proc.returncode == 2, proc
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "csl_clean.train" in errors[0] and "dtype 'O8' is not a plain numeric" in errors[0]
    assert not (store / "runs").exists()


# bombs -------------------------------------------------------------------------------------------

def test_range_is_refused_not_materialised(tmp_path):
    raw = pickle.dumps({"smplx": range(2_000_000_000)}, protocol=4)
    assert len(raw) < 80  # 16 GB of float64 once converted
    path = tmp_path / "clip.pkl"
    path.write_bytes(raw)
    with pytest.raises(InputError, match="refusing to unpickle builtins.range"):
        load(path)


def test_memo_reference_bomb_is_refused_on_the_stream(tmp_path, capsys):
    """One row referenced 100k times: 18 M float64 once converted, a few KB gzip-compressed."""
    row = [0.0] * 182
    raw = gzip.compress(pickle.dumps({"smplx": [row] * 100_000}, protocol=4), 9)
    assert len(raw) < 20_000
    path = tmp_path / "clip.pkl"
    path.write_bytes(raw)
    with pytest.raises(InputError, match="shared references count each use"):
        load(path)
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err


def test_doubling_memo_bomb_of_a_few_bytes_is_refused():
    """Each level holds the previous twice: 2^40 floats from ~300 bytes."""
    value: list = [0.0]
    for _ in range(40):
        value = [value, value]
    raw = pickle.dumps({"smplx": value}, protocol=2)
    assert len(raw) < 1000
    with pytest.raises(PickleRefused, match="exceeds the limit"):
        loads(raw, pickle_budget())


def _deep(depth: int) -> bytes:
    """{'smplx': [[[...[0.0]...]]]} nested `depth` lists deep (too deep for pickle.dumps)."""
    return (b"\x80\x02}X\x05\x00\x00\x00smplx" + b"(" * depth + b"G" + struct.pack(">d", 0.0)
            + b"l" * depth + b"s.")


def test_deep_nesting_is_one_line_exit_2(tmp_path, capsys):
    path = tmp_path / "clip.pkl"
    path.write_bytes(_deep(100_000))
    with pytest.raises(InputError, match="nested deeper than 32 levels"):
        read_pickle(path)
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert loads(_deep(20), BUDGET)["smplx"] is not None  # moderate nesting still reads


def test_ragged_fps_is_one_line_exit_2(tmp_path, capsys):
    path = tmp_path / "clip.pkl"
    path.write_bytes(pickle.dumps({"smplx": np.zeros((T, 182)), "fps": [[24.0, 25.0], [30.0]]}))
    with pytest.raises(InputError, match="field 'fps'"):
        load(path)
    assert main(["inspect", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "'fps'" in err


def test_max_frames_is_checked_before_the_float_copy(tmp_path):
    limits = IOConfig(max_frames=1000)
    rng = np.random.default_rng(0)
    cases = {  # each would be a (rows, 182) float64 copy
        "array": (np.zeros((1100, 182)), "1100 frames exceeds io.max_frames=1000"),
        "list": (rng.normal(size=(2000, 182)).tolist(), "exceeds the limit of 256000"),
        "short-rows": (np.zeros((1100, 100)).tolist(), "field 'smplx': 1100 frames exceeds"),
    }
    for name, (smplx, message) in cases.items():
        path = tmp_path / f"{name}.pkl"
        path.write_bytes(pickle.dumps({"smplx": smplx}, protocol=4))
        with pytest.raises(InputError, match=message):
            load(path, limits=limits)
    path = tmp_path / "ok.pkl"
    path.write_bytes(pickle.dumps({"smplx": np.zeros((900, 182)).tolist()}, protocol=4))
    assert load(path, limits=limits).num_frames == 900


@pytest.mark.parametrize("raw, message", [
    (b"\x80\x02" + b"N" * 200 + b".", "stack deeper than 100"),
    (b"\x80\x02" + b"]" + b"q\x00" + b"".join(b"r" + struct.pack("<I", i) for i in range(1, 5000))
     + b".", "memo entries"),
    (b"\x80\x02" + b"]0" * 5000 + b"N.", "containers"),
    (b"\x80\x02]q\x00h\x00a.", "stored in itself"),
    (b"\x80\x02]q\x00]q\x01h\x00a0h\x01a.", "changed after it was stored"),
    (b"\x80\x05" + pickle.dumps(np.arange(3), protocol=5, buffer_callback=list().append)[2:],
     "NEXT_BUFFER"),
    (pickle.dumps(collections.Counter(a=1), protocol=2), "collections.Counter"),
    (b"\x80\x02cnumpy\nndarray\nK\x02\x85\x85R.", "unsupported arguments to numpy.ndarray"),
    (b"\x80\x02cnumpy\ndtype\nX\x02\x00\x00\x00O8\x85R.", "not a plain numeric"),
], ids=["stack", "memo", "containers", "self-append", "cycle", "out-of-band", "counter",
        "ndarray-call", "object-dtype"])
def test_stream_limits_and_refusals(raw, message):
    budget = Budget(max_bytes=1 << 20, max_elements=100)
    with pytest.raises(PickleRefused, match=message):
        loads(raw, budget)


def test_file_over_the_byte_limit_is_refused_before_reading_it_all(tmp_path):
    path = tmp_path / "big.pkl"
    path.write_bytes(pickle.dumps(np.zeros(10_000), protocol=4))
    with pytest.raises(InputError, match="larger than the limit of 1000 bytes"):
        read_pickle(path, budget=Budget(max_bytes=1000, max_elements=1 << 20))


# real pickles ------------------------------------------------------------------------------------

def _numpy1(raw: bytes) -> bytes:
    """A numpy-2 pickle rewritten to numpy 1.x module names (`numpy.core.*`)."""
    count = 0
    for new in ("numpy.core.multiarray", "numpy.core.numeric"):
        old = new.replace("numpy.core", "numpy._core")
        if raw[:1] == b"\x80" and raw[1] >= 4:
            a, b = old.encode(), new.encode()
            count += raw.count(b"\x8c" + bytes([len(a)]) + a)
            raw = raw.replace(b"\x8c" + bytes([len(a)]) + a, b"\x8c" + bytes([len(b)]) + b)
        else:
            raw = raw.replace(old.encode() + b"\n", new.encode() + b"\n")
    if count and raw[2:3] == b"\x95":
        (size,) = struct.unpack("<Q", raw[3:11])
        raw = raw[:3] + struct.pack("<Q", size - count) + raw[11:]
    return raw


def _values() -> dict:
    rng = np.random.default_rng(7)
    shared = [1, 2.5, "x"]
    return {"smplx": rng.normal(size=(T, 182)).astype(np.float32),
            "fortran": np.asfortranarray(rng.normal(size=(3, 4))),
            "strided": rng.normal(size=(6, 4))[::2], "big_endian": np.arange(5, dtype=">i4"),
            "empty": np.zeros((0, 3)), "zero_d": np.array(7.5), "flags": np.array([True, False]),
            "u8": np.arange(4, dtype=np.uint8), "c": np.array([1 + 2j], np.complex64),
            "text": np.array(["ab", "c"]), "bytes_arr": np.array([b"x", b"yz"]),
            "fps": np.float64(24.0), "n": np.int64(-6), "yes": np.bool_(True),
            "gender": "neutral", "raw": b"\x00\xff", "empty_raw": b"", "ba": bytearray(b"q"),
            "od": collections.OrderedDict(b=1, a=[2]), "set": {1, 2}, "frozen": frozenset({3}),
            "cplx": 1 - 2j, "tuple": (1, None, True, 2.5), "big": 10 ** 40, "rows": [[1.0, 2.0]],
            "shared": [shared, shared]}


def _assert_same(back, ref) -> None:
    assert set(back) == set(ref)
    for key, want in ref.items():
        got = back[key]
        if isinstance(want, np.ndarray):
            assert isinstance(got, np.ndarray) and got.dtype == want.dtype, key
            assert got.shape == want.shape and got.flags.writeable, key
            np.testing.assert_array_equal(got, want)
        else:
            assert got == want, key
            if not isinstance(want, collections.OrderedDict):
                assert type(got) is type(want), key
            if isinstance(want, np.generic):
                assert got.dtype == want.dtype, key


@pytest.mark.parametrize("protocol", range(6))
@pytest.mark.parametrize("layout", ["numpy2", "numpy1"])
def test_real_pickles_round_trip_every_protocol(protocol, layout):
    raw = pickle.dumps(_values(), protocol=protocol)
    if layout == "numpy1":
        raw = _numpy1(raw)
        assert b"numpy.core" in raw and b"numpy._core" not in raw
    back = loads(raw, BUDGET)
    _assert_same(back, pickle.loads(pickle.dumps(_values(), protocol=protocol)))
    assert back["shared"][0] is back["shared"][1]  # a shared reference stays one object


def test_python2_style_pickle_with_text_buffers_loads():
    """Python 2 numpy pickles carry array and scalar bytes as `str` (SHORT_BINSTRING, read as
    latin-1) and the dtype flags as ints."""
    data = np.array([1.5, -2.0, 3.25], np.float32).tobytes()
    scalar = struct.pack("<d", 24.0)

    def s(text: bytes) -> bytes:
        return b"U" + bytes([len(text)]) + text

    dtype = lambda spec: (b"cnumpy\ndtype\n" + s(spec) + b"K\x00K\x01\x87R"  # noqa: E731
                          + b"(K\x03" + s(b"<") + b"NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb")
    raw = (b"\x80\x02}(" + s(b"smplx") + b"cnumpy.core.multiarray\n_reconstruct\n"
           + b"cnumpy\nndarray\nK\x00\x85" + s(b"b") + b"\x87R"
           + b"(K\x01K\x03\x85" + dtype(b"f4") + b"K\x00" + s(data) + b"tb"
           + s(b"fps") + b"cnumpy.core.multiarray\nscalar\n" + dtype(b"f8") + s(scalar) + b"\x86R"
           + b"u.")
    back = loads(raw, BUDGET)
    np.testing.assert_array_equal(back["smplx"], [1.5, -2.0, 3.25])
    assert back["smplx"].dtype == np.float32 and back["fps"] == 24.0


def test_signavatars_soke_and_gmr_files_still_load(tmp_path):
    rng = np.random.default_rng(1)
    smplx = rng.normal(0, 0.2, (T, 182)).astype(np.float32)
    smplx[:, 179:] = 0
    clip = tmp_path / "clip.pkl"
    clip.write_bytes(pickle.dumps({"smplx": smplx, "fps": np.float64(25.0)}, protocol=2))
    motion = load(clip)
    assert motion.num_frames == T and motion.fps == 25.0
    seq = tmp_path / "soke" / "poses" / "s1"
    seq.mkdir(parents=True)
    for i in range(3):
        (seq / f"{i:03d}.pkl").write_bytes(pickle.dumps(_frame(), protocol=4))
    split = [{"name": "s1", "text": "hello", "len": np.int64(3)}]
    (tmp_path / "soke" / "csl_clean.train").write_bytes(gzip.compress(pickle.dumps(split, 4)))
    ds = load_dataset(tmp_path / "soke", "train")
    assert ds.ids == ["s1"] and ds[0].text == "hello" and ds[0].load().num_frames == 3
    gmr = tmp_path / "motion.pkl"
    dof = rng.normal(size=(T, 29))
    gmr.write_bytes(pickle.dumps({"fps": 50, "root_pos": np.zeros((T, 3)),
                                  "root_rot": np.tile([0, 0, 0, 1.0], (T, 1)), "dof_pos": dof,
                                  "local_body_pos": None, "link_body_list": None}, protocol=4))
    np.testing.assert_array_equal(read_gmr(gmr)["dof_pos"], dof)


# fuzzing ------------------------------------------------------------------------------------------

FUZZ = r'''
import collections, os, pickle, pickletools, random, sys, tempfile
from pathlib import Path
import numpy as np
from embody.errors import InputError
from embody.io.fields import read_pickle
from embody.io.safe_pickle import Budget, PickleRefused, loads

CASES = int(sys.argv[1])
rng = random.Random(int(sys.argv[2]))
budget = Budget(max_bytes=1 << 20, max_elements=1 << 16)
PLAIN = (dict, list, tuple, set, frozenset, str, bytes, bytearray, int, float, complex, bool,
         type(None), np.ndarray, np.generic, np.dtype)


class Call:
    def __init__(self, fn, *args): self.fn, self.args = fn, args
    def __reduce__(self): return self.fn, self.args


def problem(value):
    """Why `value` is not plain data (None when it is)."""
    stack, seen = [value], set()
    while stack:
        v = stack.pop()
        if id(v) in seen:
            continue
        seen.add(id(v))
        if not isinstance(v, PLAIN):
            return f"built a {type(v).__name__}"
        dtype = v if isinstance(v, np.dtype) else getattr(v, "dtype", None)
        if dtype is not None and (dtype.kind not in "biufcSU" or dtype.hasobject):
            return f"built dtype {dtype}"
        if isinstance(v, dict):
            stack.extend(v.keys()); stack.extend(v.values())
        elif isinstance(v, (list, tuple, set, frozenset)):
            stack.extend(v)
    return None


r = np.random.default_rng(0)
row = [0.5, 1.5]
objects = [
    {"smplx": r.normal(size=(4, 182)).astype(np.float32), "fps": np.float64(24.0),
     "gender": "neutral", "tags": np.array(["a", "bc"]), "n": np.int64(3)},
    [{"name": f"s{i}", "text": "hello", "len": np.int64(i)} for i in range(3)],
    {"od": collections.OrderedDict(a=1), "set": {1, 2}, "fz": frozenset({3}), "c": 1 + 2j,
     "b": b"xy", "ba": bytearray(b"z"), "rows": [row, row], "t": (1, (2, [3.0])),
     "f": np.asfortranarray(np.ones((2, 3))), "be": np.arange(3, dtype=">i2"), "big": 10 ** 30},
    {"smplx": Call(np.ndarray, (2,), np.dtype("O"), b"A" * 16)},
    {"r": Call(range, 10 ** 9)},
]
seeds = [pickle.dumps(o, protocol=p) for o in objects for p in range(6)]
seeds += [s.replace(b"numpy._core", b"numpy.core") for s in seeds if s[1:2] < b"\x04"]
codes = [op.code.encode("latin-1") for op in pickletools.opcodes]


def spans(raw):
    starts = []
    try:
        for _, _, pos in pickletools.genops(raw):
            starts.append(pos)
    except Exception:
        pass
    starts.append(len(raw))
    return [(a, b) for a, b in zip(starts, starts[1:])] or [(0, len(raw))]


def mutate(raw):
    for _ in range(rng.randint(1, 3)):
        sp = spans(raw)
        a, b = rng.choice(sp)
        kind = rng.randrange(8)
        if kind == 0:  # delete an opcode
            raw = raw[:a] + raw[b:]
        elif kind == 1:  # duplicate an opcode
            raw = raw[:b] + raw[a:b] + raw[b:]
        elif kind == 2:  # insert a random opcode with random argument bytes
            raw = raw[:a] + rng.choice(codes) + rng.randbytes(rng.randrange(10)) + raw[a:]
        elif kind == 3 and b - a > 1:  # corrupt an opcode's argument
            i = rng.randrange(a + 1, b)
            raw = raw[:i] + rng.randbytes(rng.randint(1, min(4, b - i))) + raw[i + 4:]
        elif kind == 4:  # swap two opcodes
            c, d = rng.choice(sp)
            if (a, b) != (c, d):
                (a, b), (c, d) = sorted([(a, b), (c, d)])
                if b <= c:
                    raw = raw[:a] + raw[c:d] + raw[b:c] + raw[a:b] + raw[d:]
        elif kind == 5 and raw:  # flip random bytes
            data = bytearray(raw)
            for _ in range(rng.randint(1, 4)):
                data[rng.randrange(len(data))] ^= rng.randrange(1, 256)
            raw = bytes(data)
        elif kind == 6:  # truncate
            raw = raw[:rng.randrange(len(raw) + 1)]
        else:  # splice an opcode from another seed
            other = rng.choice(seeds)
            c, d = rng.choice(spans(other))
            raw = raw[:a] + other[c:d] + raw[a:]
    return raw


loaded = refused = 0
tmp = Path(tempfile.mkdtemp())
for case in range(CASES):
    raw = mutate(rng.choice(seeds))
    try:
        if case % 50 == 0:  # through the file reader too: every failure an InputError
            (tmp / "f.pkl").write_bytes(raw)
            try:
                out = read_pickle(tmp / "f.pkl", budget=budget)
            except InputError as exc:
                assert "\n" not in str(exc)
                raise PickleRefused(str(exc)) from None
        else:
            out = loads(raw, budget)
    except PickleRefused as exc:
        assert "\n" not in str(exc), str(exc)
        refused += 1
        continue
    except BaseException as exc:
        print(f"FAIL case {case}: {type(exc).__name__}: {exc} raw={raw.hex()}")
        sys.exit(1)
    why = problem(out)
    if why:
        print(f"FAIL case {case}: {why} raw={raw.hex()}")
        sys.exit(1)
    loaded += 1
print(f"RESULT cases={CASES} loaded={loaded} refused={refused}")
'''


def test_fuzzed_pickles_load_plain_data_or_are_refused():
    """Seeded opcode-level mutations (delete, duplicate, insert, corrupt, swap, splice) and byte
    flips of real and hostile pickles: each one is plain data or a one-line refusal, never
    another exception; a crash fails this test rather than killing pytest."""
    env = {**__import__("os").environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", FUZZ, "3000", "2026"], capture_output=True,
                          text=True, timeout=600, env=env, cwd=ROOT)
    assert proc.returncode == 0, (proc.returncode, proc.stdout[-2000:], proc.stderr[-2000:])
    result = proc.stdout.strip().splitlines()[-1]
    fields = dict(kv.split("=") for kv in result.split()[1:])
    assert fields["cases"] == "3000"
    assert int(fields["loaded"]) > 100 and int(fields["refused"]) > 100, result
