"""`embody.jit_cache.load_cached_kernels`: a new process gets the kernels numba cached on disk
before their first call, and never compiles one it has no valid cache entry for."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

KERNELS = '''
from numba import njit


@njit(cache=True)
def twice(x):
    return 2 * x


@njit(cache=True)
def never_called(x):
    return x + 1
'''

PROBE = '''
import json, sys
sys.path.insert(0, sys.argv[1])
import kernels
from embody.jit_cache import load_cached_kernels
if sys.argv[2] == "call":
    kernels.twice(3); kernels.twice(2.5)
loaded = load_cached_kernels([kernels]) if sys.argv[2] == "load" else 0
print(json.dumps({"loaded": loaded,
                  "twice": sorted(str(s) for s in kernels.twice.signatures),
                  "never_called": len(kernels.never_called.signatures),
                  "value": kernels.twice(21) if sys.argv[2] == "load" else None,
                  "hits": {str(k): v for k, v in kernels.twice.stats.cache_hits.items()},
                  "misses": {str(k): v for k, v in kernels.twice.stats.cache_misses.items()}}))
'''


def _probe(folder: Path, mode: str) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(folder / "cache"))
    out = subprocess.run([sys.executable, "-c", PROBE, str(folder), mode], env=env,
                         capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_cached_overloads_load_before_the_first_call(tmp_path):
    (tmp_path / "kernels.py").write_text(textwrap.dedent(KERNELS))
    nothing = _probe(tmp_path, "load")  # an empty cache: nothing to load, nothing compiled
    assert nothing["loaded"] == 0 and nothing["twice"] == []  # nothing before the call
    assert nothing["misses"] == {"(int64,)": 1}  # which compiled it
    _probe(tmp_path, "call")  # fills the cache: int64 and float64
    warm = _probe(tmp_path, "load")
    assert warm["loaded"] == 2
    assert warm["twice"] == ["(float64,)", "(int64,)"]
    assert warm["hits"] == {"(float64,)": 1, "(int64,)": 1} and warm["misses"] == {}
    assert warm["value"] == 42 and warm["never_called"] == 0


def test_a_changed_kernel_is_not_loaded_from_its_stale_entry(tmp_path):
    (tmp_path / "kernels.py").write_text(textwrap.dedent(KERNELS))
    _probe(tmp_path, "call")
    source = (tmp_path / "kernels.py").read_text().replace("return 2 * x", "return 3 * x")
    (tmp_path / "kernels.py").write_text(source)
    os.utime(tmp_path / "kernels.py", (1, 1))  # a new source stamp, whatever the clock
    stale = _probe(tmp_path, "load")
    assert stale["loaded"] == 0 and stale["value"] == 63  # compiled afresh at the call
