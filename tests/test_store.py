"""The artifact store: content keys, atomic publish (also under kill), verify, gc, manifests."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from embody.cli import main
from embody.config import Config
from embody.store import ArtifactStore, Manifest, arrays_checksum, content_key, files_key
from embody.tasks.stages import COLLIDE, RETARGET, SHAPE_FIT
from s3_server import StallingProxy, s3_endpoint, s3_url, store_root  # noqa: F401 (fixtures)

K1, K2 = "a" * 64, "b" * 64


def _arrays(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"q": rng.normal(size=(20, 7)).astype(np.float32), "n": np.arange(5)}


# -- content keys ------------------------------------------------------------------------------
def test_content_key_changes_exactly_with_its_ingredients():
    base = content_key("ik", "1", {"ik": '{"a":1}'}, {"collide": K1, "fit": K2})
    assert base == content_key("ik", "1", {"ik": '{"a":1}'}, {"fit": K2, "collide": K1})
    variants = [content_key("ik2", "1", {"ik": '{"a":1}'}, {"collide": K1, "fit": K2}),
                content_key("ik", "2", {"ik": '{"a":1}'}, {"collide": K1, "fit": K2}),
                content_key("ik", "1", {"ik": '{"a":2}'}, {"collide": K1, "fit": K2}),
                content_key("ik", "1", {"ik": '{"a":1}'}, {"collide": K2, "fit": K2})]
    assert len({base, *variants}) == 5


def test_step_keys_follow_only_their_own_config_sections():
    a = Config()
    b = Config.model_validate({"robot": {"name": "some_other_robot"}})
    inputs = {"source": K1}
    assert COLLIDE.key(a, inputs) == COLLIDE.key(b, inputs)  # collide reads body + collision
    assert SHAPE_FIT.key(a, {}) != SHAPE_FIT.key(b, {})
    ret = {"collide": K1, "shape_fit": K2}
    assert RETARGET.key(a, ret) != RETARGET.key(b, ret)
    # downstream of a changed key changes too, even with the same config
    assert RETARGET.key(a, ret) != RETARGET.key(a, {"collide": K1, "shape_fit": K1})


def test_files_key_hashes_bytes_not_names(tmp_path):
    (tmp_path / "a.npz").write_bytes(b"motion-1")
    (tmp_path / "b.npz").write_bytes(b"motion-1")
    (tmp_path / "c.npz").write_bytes(b"motion-2")
    assert files_key([tmp_path / "a.npz"]) == files_key([tmp_path / "b.npz"])
    assert files_key([tmp_path / "a.npz"]) != files_key([tmp_path / "c.npz"])
    assert files_key([tmp_path / "a.npz"]) != files_key([tmp_path / "a.npz"], extra="hello")


# -- publish / read ----------------------------------------------------------------------------
def test_publish_roundtrip_and_metadata(tmp_path):
    store = ArtifactStore(tmp_path)
    arrays = _arrays()
    assert not store.has("ik", K1)
    assert store.publish("ik", K1, arrays, {"fps": 30.0, "x": np.float64(2.5)},
                         {"inputs": {"collide": K2}, "metrics": {"err": np.float32(1.5)}})
    assert store.has("ik", K1)
    assert store.path("ik", K1) == tmp_path.resolve() / "artifacts" / "ik" / "aa" / K1
    art = store.read("ik", K1)
    for name, a in arrays.items():
        np.testing.assert_array_equal(art.arrays[name], a)
        assert art.arrays[name].dtype == a.dtype
    assert art.attrs == {"fps": 30.0, "x": 2.5}
    assert art.info["inputs"] == {"collide": K2}
    assert art.info["metrics"] == {"err": 1.5}
    assert art.info["checksum"] == arrays_checksum(arrays)
    assert "numpy" in art.info["versions"] and art.info["host"]
    assert store.info("ik", K1)["status"] == "ok"
    assert not store.publish("ik", K1, _arrays(1), {}, {})  # already there: first writer wins
    np.testing.assert_array_equal(store.read("ik", K1).arrays["q"], arrays["q"])
    assert list(store.entries()) == [("ik", K1, store.path("ik", K1))]


def test_publish_writes_the_files_zarr_writes(tmp_path):
    """`publish` encodes in memory and writes the files itself: the same files, byte for byte,
    as zarr's own LocalStore writes for the same arrays and attrs (folder order included in
    the recorded `files`: names sorting differently as strings and as paths)."""
    import zarr
    store = ArtifactStore(tmp_path / "store")
    arrays = {"q": np.linspace(0, 1, 12).reshape(4, 3), "scalar": np.float32(2.5),
              "png": np.frombuffer(b"\x89PNG" * 7, np.uint8), "zeros": np.zeros((3, 2)),
              "flags": np.array([True, False, True]), "ids": np.arange(5, dtype=np.int64),
              "a-b": np.ones(2), "a": np.full((2, 2), np.nan, np.float32), "a.c": np.ones(3)}
    assert store.publish("ik", K1, arrays, {"fps": 30.0}, {"inputs": {}})
    ours = store.path("ik", K1)
    ref = tmp_path / "ref"
    group = zarr.open_group(str(ref), mode="w", zarr_format=3)
    for name, a in arrays.items():
        a = np.ascontiguousarray(a)
        arr = group.create_array(name, shape=a.shape, dtype=a.dtype,
                                 chunks=a.shape if a.ndim else (), overwrite=True)
        arr[...] = a
    files = {p.relative_to(ref).as_posix(): p.stat().st_size
             for p in sorted(ref.rglob("*")) if p.is_file() and p.name != "zarr.json"}
    attributes = json.loads((ours / "zarr.json").read_text())["attributes"]
    assert attributes["embody"]["files"] == files
    assert list(attributes["embody"]["files"]) == list(files)  # same order
    group.attrs.update(attributes)
    listing = sorted(p.relative_to(ref).as_posix() for p in ref.rglob("*") if p.is_file())
    assert listing == sorted(p.relative_to(ours).as_posix() for p in ours.rglob("*")
                             if p.is_file())
    for rel in listing:
        assert (ours / rel).read_bytes() == (ref / rel).read_bytes(), rel
    art = store.read("ik", K1)
    for name, a in arrays.items():
        np.testing.assert_array_equal(art.arrays[name], a)
    assert store.intact("ik", K1) and store.verify("ik", K1) is None


def test_store_rejects_urls_it_does_not_serve(tmp_path):
    from embody.errors import ConfigError
    for url in ("http://example.com/store", "ftp://host/store", "s3://", "file://otherhost/x"):
        with pytest.raises(ConfigError):
            ArtifactStore(url)
    assert ArtifactStore(f"file://{tmp_path}").root == tmp_path.resolve()
    assert ArtifactStore("s3://bucket/prefix/").url == "s3://bucket/prefix"


def test_concurrent_writers_one_winner_no_leftovers(store_root):
    store = ArtifactStore(store_root)
    results, barrier = [], threading.Barrier(6)

    def write(i: int) -> None:
        barrier.wait()
        results.append(store.publish("collide", K1, _arrays(i), {"writer": i}, {}))

    threads = [threading.Thread(target=write, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sum(results) == 1
    winner = store.read("collide", K1)
    assert store.verify("collide", K1) is None
    np.testing.assert_array_equal(winner.arrays["q"], _arrays(winner.attrs["writer"])["q"])
    assert store.stale_temps(max_age_s=0) == []  # the losers left nothing behind
    if store.is_local:
        assert [p.name for p in store.path("collide", K1).parent.iterdir()] == [K1]


_SLOW_WRITER = """
import sys, numpy as np
from embody.store import ArtifactStore
rng = np.random.default_rng(0)
side = int(sys.argv[3])
arrays = {f"a{i:03d}": rng.normal(size=(side, 1024)) for i in range(150)}
ArtifactStore(sys.argv[1]).publish("render", sys.argv[2], arrays, {}, {})
print("finished")
"""


def _writing(store: ArtifactStore, step: str, key: str) -> bool:
    """A writer has begun to put the artifact's files (its temp folder)."""
    parent = store.path(step, key).parent
    return parent.is_dir() and any(parent.iterdir())


def test_killed_writer_leaves_no_hit_and_rerun_completes(store_root):
    """Killed half way through writing (a local temp folder, or an object store's one PUT
    stalled half sent by a relay), a writer leaves no hit; a rerun publishes; gc tidies."""
    store = ArtifactStore(store_root)
    side, env, relay = "256", None, None
    if not store.is_local:
        side = "8"
        relay = StallingProxy(os.environ["AWS_ENDPOINT_URL"], stall_after=1 << 20)
        env = {**os.environ, "AWS_ENDPOINT_URL": relay.url}
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_WRITER, store_root, K1, side],
                            stdout=subprocess.PIPE, env=env)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not (
            relay.stalled.is_set() if relay else _writing(store, "render", K1)):
        time.sleep(0.005)
    time.sleep(0.05)
    assert proc.poll() is None, "writer finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    if relay:
        relay.__exit__()  # the server's side of the upload is cut too
    assert not store.has("render", K1)
    assert list(store.entries()) == []
    temps = store.stale_temps(max_age_s=0 if relay else 24 * 3600)
    if store.is_local:
        assert len(temps) == 1 and str(temps[0]).startswith(str(store.path("render", K1)))
    else:  # an object store applies a PUT whole or not at all
        assert temps == [] and store.size(store.path("render", K1)) == 0
    # a rerun publishes normally; gc clears the dead writer's temp
    assert store.publish("render", K1, _arrays(), {}, {})
    assert main(["store", "gc", "--store", store_root, "--json"]) == 0
    assert all(store.size(t) == 0 for t in temps) and store.stale_temps(max_age_s=0) == []


# -- verify and gc -----------------------------------------------------------------------------
def test_verify_detects_a_corrupted_chunk(tmp_path, capsys):
    store = ArtifactStore(tmp_path)
    store.publish("ik", K1, _arrays(), {}, {})
    store.publish("ik", K2, _arrays(1), {}, {})
    assert main(["store", "verify", "--store", str(tmp_path)]) == 0
    chunk = next(p for p in (store.path("ik", K2) / "q").rglob("*") if p.is_file()
                 and p.name != "zarr.json")
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    assert store.verify("ik", K1) is None
    assert store.verify("ik", K2) is not None
    capsys.readouterr()
    assert main(["store", "verify", "--store", str(tmp_path), "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["checked"] == 2
    assert [(c["step"], c["key"]) for c in report["corrupt"]] == [("ik", K2)]


def test_gc_removes_only_unreferenced_artifacts(tmp_path, capsys):
    store = ArtifactStore(tmp_path)
    for step, key in [("source", K1), ("collide", K1), ("collide", K2), ("shape_fit", K2)]:
        store.publish(step, key, _arrays(), {}, {})
    m = Manifest(store, "r1")
    m.start(["s1"])
    m.update({"id": "s1", "keys": {"source": K1, "collide": K1}, "status": "ok"})
    m.set_shared("shape_fit", K2)
    m.finish_sequence("s1")
    m.save(finished=True)
    capsys.readouterr()
    assert main(["store", "gc", "--store", str(tmp_path), "--dry-run", "--json"]) == 0
    dry = json.loads(capsys.readouterr().out)
    assert dry["removed"] == [{"step": "collide", "key": K2}]
    assert store.has("collide", K2)
    assert main(["store", "gc", "--store", str(tmp_path)]) == 0
    assert sorted((s, k) for s, k, _ in store.entries()) == [
        ("collide", K1), ("shape_fit", K2), ("source", K1)]
    capsys.readouterr()
    assert main(["store", "ls", "--store", str(tmp_path), "--json"]) == 0
    listing = json.loads(capsys.readouterr().out)
    assert listing["steps"]["collide"]["artifacts"] == 1
    assert listing["runs"]["r1"] == {"sequences": 1, "ok": 1, "failed": 0, "pending": 0,
                                     "finished": True}


def test_manifest_is_rewritten_atomically(tmp_path):
    store = ArtifactStore(tmp_path)
    m = Manifest(store, "run-a")
    m.start(["x", "y"], dataset="d")
    m.update({"id": "x", "keys": {"source": K1}, "metrics": {"source": {"frames": 3}},
              "status": "ok"})
    m.update({"id": "y", "keys": {"source": K2}, "status": "failed", "error": "boom",
              "failed_step": "collide"})
    m.finish_sequence("x")
    m.finish_sequence("y")
    m.save()
    loaded = Manifest.load(store, "run-a")
    assert loaded.sequences["x"] == {"status": "ok", "error": None, "failed_step": None,
                                     "steps": {"source": K1},
                                     "metrics": {"source": {"frames": 3}}}
    assert loaded.sequences["y"]["status"] == "failed"
    assert loaded.keys() == {("source", K1), ("source", K2)}
    assert [p.name for p in m.path.parent.iterdir()] == ["manifest.json"]


def test_computation_counters_append_whole_lines(tmp_path):
    store = ArtifactStore(tmp_path)
    threads = [threading.Thread(target=lambda i=i: [store.record("ik", f"{i}-{j}", sequence="s")
                                                    for j in range(50)]) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    rows = store.computations("ik")
    assert len(rows) == 200 and len({r["key"] for r in rows}) == 200
    assert store.computations("nothing") == []


def test_robot_definition_bytes_enter_robot_step_keys(tmp_path):
    robots = tmp_path / "robots"
    robots.mkdir()
    (robots / "bot.yaml").write_text("a: 1\n")
    cfg = Config.model_validate({"robot": {"name": "bot", "robots_dir": str(robots)}})
    before = SHAPE_FIT.key(cfg, {}), COLLIDE.key(cfg, {"source": K1})
    (robots / "bot.yaml").write_text("a: 2\n")
    after = SHAPE_FIT.key(cfg, {}), COLLIDE.key(cfg, {"source": K1})
    assert before[0] != after[0] and before[1] == after[1]
