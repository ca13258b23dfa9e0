"""The store on an S3-compatible server (moto, over HTTP on localhost): what only an object
store needs showing. The local store's own tests (publish races, a killed writer, manifest
merges) also run on S3 through the `store_root` fixture in test_store.py and
test_concurrent_runs.py."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from embody.cli import main
from embody.errors import ConfigError
from embody.store import ArtifactStore, CorruptArtifact, Manifest
from embody.store.claims import claim_run
from s3_server import s3_endpoint, s3_url  # noqa: F401 (fixtures)

K1, K2, K3 = "a" * 64, "b" * 64, "c" * 64
ROOT = Path(__file__).resolve().parents[1]


def _arrays(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"q": rng.normal(size=(20, 7)).astype(np.float32), "n": np.arange(5)}


def test_roundtrip_through_the_s3_api(s3_url):
    store = ArtifactStore(s3_url)
    assert not store.is_local and not store.exists() and not store.has("ik", K1)
    assert store.publish("ik", K1, _arrays(), {"fps": 30.0}, {"inputs": {"collide": K2}})
    assert not store.publish("ik", K1, _arrays(1), {}, {})  # first writer wins
    fresh = ArtifactStore(s3_url)  # another process' view: nothing remembered
    art = fresh.read("ik", K1)
    np.testing.assert_array_equal(art.arrays["q"], _arrays()["q"])
    assert art.attrs == {"fps": 30.0} and art.info["inputs"] == {"collide": K2}
    assert fresh.intact("ik", K1) and fresh.verify("ik", K1) is None
    assert [(s, k) for s, k, _ in fresh.entries()] == [("ik", K1)]
    assert fresh.path("ik", K1) == f"{s3_url}/artifacts/ik/aa/{K1}"
    fresh.record("ik", K1, sequence="s1")
    assert [r["sequence"] for r in store.computations("ik")] == ["s1"]


def test_an_artifact_is_one_object_zarr_reads(s3_url, tmp_path):
    """The packed object opens with zarr's own ZipStore (no embody needed to read a result)."""
    import zarr

    store = ArtifactStore(s3_url)
    assert store.publish("ik", K1, _arrays(), {"fps": 30.0}, {})
    assert [o["path"].rsplit("/", 1)[-1] for o in store.objects.list("artifacts")] == [
        "zarr.zip"]
    (tmp_path / "a.zip").write_bytes(store.objects.get(f"artifacts/ik/aa/{K1}/zarr.zip")[0])
    group = zarr.open_group(zarr.storage.ZipStore(tmp_path / "a.zip", mode="r"), mode="r")
    np.testing.assert_array_equal(group["q"][...], _arrays()["q"])
    assert group.attrs["result"] == {"fps": 30.0}


def test_stray_or_truncated_objects_are_no_hit(s3_url):
    """Objects in an artifact's folder that are not its packed object (an upload by another
    tool or layout) are no hit, no entry, unreadable; gc takes them once a day old. A packed
    object cut short (no writer of ours leaves one: a PUT lands whole) fails the hit check."""
    store = ArtifactStore(s3_url)
    blobs = store._encode("ik", K1, _arrays(), {}, {})
    folder = f"artifacts/ik/aa/{K1}/deadhost-999999-0000abcd"
    store.objects.put_many({f"{folder}/{rel}": data for rel, data in blobs.items()})
    assert store.size(store.path("ik", K1)) > 0
    assert not store.has("ik", K1) and list(store.entries()) == []
    with pytest.raises(CorruptArtifact):
        store.read("ik", K1)
    assert store.stale_temps() == []  # kept until it is a day old
    assert store.stale_temps(max_age_s=0) == [f"{s3_url}/{folder}"]
    assert main(["store", "verify", "--store", s3_url]) == 0
    assert store.publish("ik", K1, _arrays(), {}, {})  # a rerun publishes beside it
    assert store.read("ik", K1).arrays["n"].tolist() == [0, 1, 2, 3, 4]
    for stray in store.stale_temps(max_age_s=0):  # what gc does with a day-old one
        store.remove_path(stray)
    assert store.stale_temps(max_age_s=0) == [] and store.intact("ik", K1)
    whole = store.objects.get(f"artifacts/ik/aa/{K1}/zarr.zip")[0]
    store.objects.put(f"artifacts/ik/aa/{K1}/zarr.zip", whole[:-100])
    fresh = ArtifactStore(s3_url)
    assert fresh.has("ik", K1) and not fresh.intact("ik", K1)
    with pytest.raises(CorruptArtifact):
        fresh.read("ik", K1)


def test_verify_gc_and_ls_on_s3(s3_url, capsys):
    store = ArtifactStore(s3_url)
    for step, key, seed in [("source", K1, 0), ("collide", K1, 1), ("collide", K2, 2),
                            ("ik", K3, 3)]:
        store.publish(step, key, _arrays(seed), {}, {})
    m = Manifest(store, "r1")
    m.start(["s1"])
    m.update({"id": "s1", "keys": {"source": K1, "collide": K1, "ik": K3}, "status": "ok"})
    m.finish_sequence("s1")
    m.save(finished=True)
    # corrupt one byte of a chunk in place (the object keeps its length)
    packed = f"artifacts/ik/cc/{K3}/zarr.zip"
    data = bytearray(store.objects.get(packed)[0])
    data[data.index(b"q/c/0/0") + 40] ^= 0xFF
    store.objects.put(packed, bytes(data))
    capsys.readouterr()
    assert main(["store", "verify", "--store", s3_url, "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["checked"] == 4 and [(c["step"], c["key"]) for c in report["corrupt"]] == [
        ("ik", K3)]
    assert main(["store", "gc", "--store", s3_url, "--dry-run", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["removed"] == [{"step": "collide", "key": K2}]
    assert store.has("collide", K2)
    assert main(["store", "gc", "--store", s3_url, "--json"]) == 0
    capsys.readouterr()
    assert sorted((s, k) for s, k, _ in store.entries()) == [
        ("collide", K1), ("ik", K3), ("source", K1)]
    assert store.size(store.path("collide", K2)) == 0
    assert main(["store", "ls", "--store", s3_url, "--json"]) == 0
    listing = json.loads(capsys.readouterr().out)
    assert listing["steps"]["collide"]["artifacts"] == 1 and listing["steps"]["ik"]["bytes"] > 0
    assert listing["runs"]["r1"] == {"sequences": 1, "ok": 1, "failed": 0, "pending": 0,
                                     "finished": True}
    assert main(["store", "ls", "--store", s3_url + "-nothing-here"]) == 2


_SAVER = """
import sys
from embody.store import ArtifactStore, Manifest
store, me, n = ArtifactStore(sys.argv[1]), sys.argv[2], int(sys.argv[3])
m = Manifest(store, "shared")
ids = [f"{me}-{i}" for i in range(n)]
m.start(ids)
for sid in ids:
    m.update({"id": sid, "keys": {"source": "k" + sid}, "status": "ok"})
    m.finish_sequence(sid)
    m.save()
m.save(finished=True)
"""


def test_concurrent_manifest_writers_of_one_run_lose_nothing(s3_url):
    """Four processes save one run's manifest after every sequence at once: the conditional
    writes (If-Match on the version merged into) keep every sequence of every writer."""
    procs = [subprocess.Popen([sys.executable, "-c", _SAVER, s3_url, f"w{i}", "6"], cwd=ROOT)
             for i in range(4)]
    assert [p.wait(timeout=300) for p in procs] == [0] * 4
    disk = Manifest.load(ArtifactStore(s3_url), "shared")
    assert sorted(disk.sequences) == sorted(f"w{i}-{j}" for i in range(4) for j in range(6))
    assert {s["status"] for s in disk.sequences.values()} == {"ok"}
    assert disk.finished and disk.data["writers"] == {}


_HOLD = """
import sys, time
from embody.store import ArtifactStore
from embody.store.claims import claim_run
with claim_run(ArtifactStore(sys.argv[1]), "shared", {"dataset": "A", "split": None}):
    print("claimed", flush=True)
    time.sleep(120)
"""


def test_a_claim_is_a_lease_a_killed_holder_frees_at_once(s3_url):
    store = ArtifactStore(s3_url)
    proc = subprocess.Popen([sys.executable, "-c", _HOLD, s3_url], stdout=subprocess.PIPE,
                            text=True, cwd=ROOT)
    try:
        assert proc.stdout.readline().strip() == "claimed"
        with pytest.raises(ConfigError, match=f"pid {proc.pid}.*dataset 'A'"):
            with claim_run(store, "shared", {"dataset": "B", "split": None}):
                pass
        with claim_run(store, "shared", {"dataset": "A", "split": None}):
            pass  # the same data shares the name
    finally:
        proc.kill()
        proc.wait()
    t0 = time.monotonic()
    with claim_run(store, "shared", {"dataset": "B", "split": None}):
        pass  # its holder died on this host: free without waiting for the lease
    assert time.monotonic() - t0 < 5
    claim = json.loads(store.objects.get("runs/.locks/shared.claim.json")[0])
    assert claim["dataset"] == "B" and claim["holders"] == {}


def test_run_files_and_the_local_work_dir(s3_url, tmp_path, monkeypatch):
    """What flows keep beside a run (sequences.csv) goes to the bucket; what must be local
    (Prefect's home) gets a folder of its own per store URL, never a junk `./s3:/` path."""
    store = ArtifactStore(s3_url)
    where = store.write_run_file("r1", "sequences.csv", b"id,status\ns1,ok\n")
    assert where == f"{s3_url}/runs/r1/sequences.csv"
    assert store.objects.get("runs/r1/sequences.csv")[0] == b"id,status\ns1,ok\n"
    monkeypatch.setenv("EMBODY_WORK_DIR", str(tmp_path))
    assert store.work_dir.parent == tmp_path.resolve()
    assert store.work_dir != ArtifactStore(s3_url + "-other").work_dir
    local = ArtifactStore(tmp_path / "local")
    assert local.work_dir == local.root
    assert local.write_run_file("r1", "x.csv", b"a") == local.runs_dir / "r1" / "x.csv"


def test_reports_find_their_runs_on_s3(s3_url):
    """`embody report`'s reader finds runs by the store's API (no paths): the latest main run,
    a named run's manifest, one line naming the known runs for an unknown one."""
    from embody.errors import InputError
    from embody.report.reader import latest_run, open_run, sequence_text

    store = ArtifactStore(s3_url)
    store.publish("source", K1, _arrays(), {"meta": {"text": "HELLO"}}, {})
    for run in ("older", "newer", "newer.ablation-x"):
        m = Manifest(store, run)
        m.start(["s1"])
        m.update({"id": "s1", "keys": {"source": K1}, "status": "ok"})
        m.save(finished=True)
        time.sleep(1.1)  # S3 last-modified has one-second resolution
    assert latest_run(s3_url) == "newer"
    opened, manifest = open_run(s3_url, "older")
    assert manifest.sequences["s1"]["steps"] == {"source": K1}
    assert sequence_text(opened, manifest.sequences["s1"]) == "HELLO"
    with pytest.raises(InputError, match="runs: newer, newer.ablation-x, older"):
        open_run(s3_url, "missing")


_FORK = """
import os, sys
from embody.store import ArtifactStore
store = ArtifactStore(sys.argv[1])
store.has("ik", "a" * 64)  # the parent has used the client
pid = os.fork()
if pid == 0:
    try:
        ArtifactStore(sys.argv[1]).has("ik", "a" * 64)
        os._exit(3)
    except RuntimeError as exc:
        os._exit(7 if "fork" in str(exc) else 4)
_, status = os.waitpid(pid, 0)
sys.exit(os.waitstatus_to_exitcode(status))
"""


def test_a_process_forked_after_use_gets_an_error_not_a_hang(s3_url):
    """obstore's runtime does not survive fork (its requests would hang in the child)."""
    done = subprocess.run([sys.executable, "-c", _FORK, s3_url], cwd=ROOT, timeout=120)
    assert done.returncode == 7


def test_a_reader_follows_an_artifact_republished_by_another_process(s3_url):
    """A process remembers the refs it read; when another removes and republishes the key,
    the next read follows the new ref instead of reporting the artifact corrupt."""
    reader, other = ArtifactStore(s3_url), ArtifactStore(s3_url)
    assert reader.publish("ik", K1, _arrays(0), {"v": 0}, {})
    assert reader.read("ik", K1).attrs == {"v": 0}
    other.remove("ik", K1)
    assert other.publish("ik", K1, _arrays(1), {"v": 1}, {})
    art = reader.read("ik", K1)
    assert art.attrs == {"v": 1}
    np.testing.assert_array_equal(art.arrays["q"], _arrays(1)["q"])


def _npz_bytes(frames: int) -> bytes:
    import io

    out = io.BytesIO()
    np.savez(out, poses=np.zeros((frames, 165)), mocap_frame_rate=np.array(30.0))
    return out.getvalue()


def test_datasets_are_read_from_urls(s3_url, tmp_path, monkeypatch, capsys):
    """`embody run s3://…` lists and loads a dataset (a prefix, or a CSV manifest object) from
    a local mirror it keeps up to date by ETag; what is missing or bad is one line naming the
    object's URL, exit 2, before anything is written."""
    from embody.cli.run import prepare
    from embody.config import Config
    from embody.config.run import RunConfig
    from embody.io import load_dataset
    from embody.store.objects import Objects

    monkeypatch.setenv("EMBODY_WORK_DIR", str(tmp_path / "work"))
    data = Objects(f"{s3_url}/signs")
    data.put_many({"a.npz": _npz_bytes(4), "sub/b.npz": _npz_bytes(6),
                   "list.csv": b"path,text\nsub/b.npz,HELLO\n"})
    local = prepare(f"{s3_url}/signs", None, Config(run=RunConfig(store=str(tmp_path / "s"))))
    assert local.is_dir() and local.name == "signs"
    ds = load_dataset(f"{s3_url}/signs")
    assert ds.ids == ["a", "sub/b"] and ds.get("sub/b").load().num_frames == 6
    manifest = load_dataset(f"{s3_url}/signs/list.csv")
    assert manifest.ids == ["sub/b"] and manifest[0].load().meta["text"] == "HELLO"
    data.put("a.npz", _npz_bytes(9))  # changed upstream: fetched again
    assert load_dataset(f"{s3_url}/signs").get("a").load().num_frames == 9
    data.put("bad.csv", b"file,text\na.npz,x\n")
    capsys.readouterr()
    store = str(tmp_path / "store")
    for url, said in [(f"{s3_url}/signs/bad.csv", f"{s3_url}/signs/bad.csv: field 'path'"),
                      (f"{s3_url}/nothing", f"{s3_url}/nothing: no such object or prefix"),
                      (f"{s3_url}/signs/a.npz", f"{s3_url}/signs/a.npz: a dataset is a prefix")]:
        assert main(["run", url, "--store", store]) == 2
        assert said in capsys.readouterr().err
    assert not (tmp_path / "store").exists()
