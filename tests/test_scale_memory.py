"""The driver's memory at scale: saving the manifest must not hold its whole JSON text.

At 1,000 sequences the manifest is ~4.7 MB of JSON; built as one string it cost each save a
~23 MB peak (×20 at 20k sequences). `write_json_atomic` streams it instead.
"""

from __future__ import annotations

import json
import tracemalloc

from embody.store.manifest import write_json_atomic


def test_manifest_save_streams_instead_of_building_the_text(tmp_path):
    data = {"sequences": {f"seq_{i:05d}": {"status": "ok", "steps": {"source": "ab" * 32},
                                           "metrics": {"m": {f"k{j}": j * 0.1 for j in range(40)}}}
                          for i in range(1500)}}
    path = tmp_path / "runs" / "r" / "manifest.json"
    tracemalloc.start()
    try:
        write_json_atomic(path, data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    size = path.stat().st_size
    assert size > 1_500_000
    assert peak < size / 4, (peak, size)  # one string would be >= size
    assert json.loads(path.read_text(encoding="utf-8")) == data
    assert [p.name for p in path.parent.iterdir()] == ["manifest.json"]  # no temp left
