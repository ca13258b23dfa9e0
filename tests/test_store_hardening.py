"""Hostile or broken store situations (issue 10): run names, corrupt artifacts, gc after a crash,
symlinks, a full disk. All on the real store and CLI, without Prefect."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from embody.cli import main
from embody.config import Config
from embody.errors import ConfigError
from embody.store import ArtifactStore, CorruptArtifact, Manifest, check_run_name
from embody.tasks.execute import new_record, run_batch
from embody.tasks.pipeline import Context, Step
from embody.tasks.stages import SOURCE
from toy_flow import Toy

K1, K2, K3 = "ab" + "1" * 62, "cd" + "2" * 62, "ef" + "3" * 62


def _arrays(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"q": rng.normal(size=(20, 7)), "t": rng.normal(size=(20,))}


# -- run names (item 4) ----------------------------------------------------------------------------
@pytest.mark.parametrize("name", [".", "..", "...", "a/b", "../x", "", "a b"])
def test_run_names_that_escape_runs_are_refused(tmp_path, name):
    with pytest.raises(ConfigError, match="run name"):
        check_run_name(name)
    with pytest.raises(ConfigError):
        Manifest(ArtifactStore(tmp_path), name)
    assert check_run_name("synth-n24-s0.unitree_g1_dex3") == "synth-n24-s0.unitree_g1_dex3"


def test_report_export_and_run_refuse_dot_names(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    mine = tmp_path / "figures" / "mine.txt"
    mine.parent.mkdir()
    mine.write_text("not the report's")
    store = tmp_path / "store"
    for name in (".", ".."):
        assert main(["report", name, "--store", str(store)]) == 2
        assert main(["export", name, str(tmp_path / "out"), "--robot", "unitree_g1_dex3",
                     "--store", str(store)]) == 2
        assert main(["run", str(tmp_path), "--name", name, "--store", str(store)]) == 2
    assert "run name" in capsys.readouterr().err
    assert mine.read_text() == "not the report's"
    assert not store.exists()  # refused before anything was created
    assert not (tmp_path / "manifest.json").exists() and not (tmp_path / "out").exists()


def test_report_deletes_only_files_it_created(tmp_path):
    from embody.report.build import write_report
    from embody.report.data import RunData

    out = tmp_path / "rep"
    (out / "figures").mkdir(parents=True)
    (out / "figures" / "notes.txt").write_text("user file")
    seqs = pd.DataFrame({"status": ["ok"], "error": [None], "text": ["hi"]},
                        index=pd.Index(["s1"], name="id"))
    sheet = b"\x89PNG\r\n\x1a\n"  # copied verbatim
    write_report(RunData("r", seqs, sheets={"s1": sheet}), out)
    assert (out / "figures" / "sheets" / "s1.png").is_file()
    write_report(RunData("r", seqs, sheets={"s2": sheet}), out)
    assert not (out / "figures" / "sheets" / "s1.png").exists()  # its own stale figure: gone
    assert (out / "figures" / "sheets" / "s2.png").is_file()
    assert (out / "figures" / "notes.txt").read_text() == "user file"


# -- corrupt artifacts (item 8) --------------------------------------------------------------------
def _chunk(store: ArtifactStore, step: str, key: str, array: str) -> Path:
    return next(p for p in (store.path(step, key) / array).rglob("*")
                if p.is_file() and p.name != "zarr.json")


def test_reads_check_each_arrays_digest(tmp_path):
    store = ArtifactStore(tmp_path)
    store.publish("ik", K1, _arrays(), {}, {})
    store.publish("ik", K2, _arrays(1), {}, {})
    assert store.intact("ik", K1) and np.allclose(store.read("ik", K1).arrays["q"], _arrays()["q"])
    _chunk(store, "ik", K1, "q").unlink()  # zarr would read fill values (zeros)
    assert not store.intact("ik", K1)
    with pytest.raises(CorruptArtifact, match="'q'"):
        store.read("ik", K1)
    chunk = _chunk(store, "ik", K2, "t")
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    assert store.intact("ik", K2)  # same size: only the digest at load can tell
    with pytest.raises(CorruptArtifact):
        store.read("ik", K2)


COLLIDE = Step("collide", "1", ("collision",), lambda ctx, i: Toy(i["source"].pose * 2,
                                                                  {"sum": float(i["source"].pose.sum())}),
               Toy.from_arrays, (SOURCE,))
METRICS = Step("metrics", "1", (), lambda ctx, i: Toy(np.array(float(i["collide"].x.sum())),
                                                      {"total": float(i["collide"].x.sum())}),
               Toy.from_arrays, (COLLIDE,))


def _write_amass(folder: Path, n: int = 2) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        np.savez(folder / f"seq{i:03d}.npz", poses=rng.normal(0, 0.1, (5, 165)),
                 trans=np.zeros((5, 3)), betas=np.zeros(10), gender="neutral",
                 mocap_frame_rate=30.0)
    return folder


def _chain(ctx, refs, steps):
    recs = [new_record(r) for r in refs]
    for step in steps:
        recs = run_batch(step, ctx, recs, {})
    return recs


def test_a_corrupt_input_is_recomputed_and_reported(tmp_path):
    from embody.io import load_dataset

    refs = list(load_dataset(_write_amass(tmp_path / "data")))
    ctx = Context(cfg=Config(), store_root=str(tmp_path / "store"), run="r")
    store = ctx.store
    first = _chain(ctx, refs, (SOURCE, COLLIDE, METRICS))
    truth = first[0]["metrics"]["metrics"]["total"]
    keys = first[0]["keys"]
    # flip a byte of the collide and the source artifact of seq000, drop metrics to force a load
    for step in ("collide", "source"):
        chunk = next(p for p in store.path(step, keys[step]).rglob("*")
                     if p.is_file() and p.name != "zarr.json" and p.stat().st_size > 16)
        data = bytearray(chunk.read_bytes())
        data[-3] ^= 0x55
        chunk.write_bytes(bytes(data))
    store.remove("metrics", keys["metrics"])
    # the next run (a new session: what a run published, it reads from memory, `tasks.recent`)
    again = _chain(Context(cfg=Config(), store_root=str(tmp_path / "store"), run="r"), refs,
                   (SOURCE, COLLIDE, METRICS))
    assert again[0]["status"] == "ok", again[0]["error"]
    assert again[0]["metrics"]["metrics"]["total"] == pytest.approx(truth)
    recovered = " ".join(again[0]["recovered"])
    assert "collide/" in recovered and "source/" in recovered
    assert "recovered" not in again[1]
    reasons = [(r["step"], r["reason"]) for r in store.computations() if r["reason"] == "corrupt"]
    assert sorted(reasons) == [("collide", "corrupt"), ("source", "corrupt")]
    assert store.verify("collide", keys["collide"]) is None and store.verify("source", keys["source"]) is None


def test_a_deleted_chunk_is_a_cache_miss(tmp_path):
    from embody.io import load_dataset

    refs = list(load_dataset(_write_amass(tmp_path / "data")))
    ctx = Context(cfg=Config(), store_root=str(tmp_path / "store"), run="r")
    first = _chain(ctx, refs, (SOURCE, COLLIDE))
    key = first[1]["keys"]["collide"]
    _chunk(ctx.store, "collide", key, "x").unlink()
    again = _chain(ctx, refs, (SOURCE, COLLIDE))
    assert again[1]["computed"] == ["collide"] and again[0]["computed"] == []
    assert "collide/" in again[1]["recovered"][0]
    assert ctx.store.verify("collide", key) is None


# -- gc after a crash, symlinks, stale temps (items 5, 9) -------------------------------------------
def _gc(tmp_path, capsys, *extra) -> dict:
    capsys.readouterr()
    assert main(["store", "gc", "--store", str(tmp_path), "--json", *extra]) == 0
    return json.loads(capsys.readouterr().out)


def test_gc_keeps_the_work_of_an_unfinished_run(tmp_path, capsys):
    store = ArtifactStore(tmp_path)
    store.publish("collide", K1, _arrays(), {}, {"run": "crashed"})  # recorded in the manifest
    store.publish("collide", K2, _arrays(1), {}, {"run": "crashed"})  # finished, not yet recorded
    store.publish("collide", K3, _arrays(2), {}, {"run": "old"})  # nobody's
    m = Manifest(store, "crashed")
    m.start(["s1", "s2"])
    m.update({"id": "s1", "keys": {"collide": K1}, "status": "ok"})
    m.save()  # no finished stamp: killed mid-run
    out = _gc(tmp_path, capsys)
    assert out["removed"] == [{"step": "collide", "key": K3}] and out["live_runs"] == ["crashed"]
    assert store.has("collide", K2)
    out = _gc(tmp_path, capsys, "--older-than", "0s")  # the explicit override
    assert out["removed"] == [{"step": "collide", "key": K2}]
    assert store.has("collide", K1)
    assert main(["store", "gc", "--store", str(tmp_path), "--older-than", "soon"]) == 2


def test_gc_never_follows_a_symlink_out_of_the_store(tmp_path, capsys):
    outside = tmp_path / "outside"
    victim = outside / "ab" / K1
    victim.mkdir(parents=True)
    (victim / "zarr.json").write_text("{}")
    (victim / "precious.txt").write_text("keep")
    root = tmp_path / "store"
    store = ArtifactStore(root)
    store.publish("collide", K2, _arrays(), {}, {})
    (root / "artifacts" / "evil").symlink_to(outside, target_is_directory=True)
    (root / "artifacts" / "collide" / "ef").mkdir()
    (root / "artifacts" / "collide" / "ef" / K3).symlink_to(victim, target_is_directory=True)
    tmp_link = root / "artifacts" / "collide" / "cd" / f"{K2}.tmp-host-1-x"
    tmp_link.symlink_to(victim, target_is_directory=True)
    out = _gc(root, capsys)
    assert out["removed"] == [{"step": "collide", "key": K2}]
    assert (victim / "precious.txt").read_text() == "keep"
    with pytest.raises(ValueError):
        store.remove_path(root / "artifacts" / "evil" / "ab" / K1)
    assert victim.is_dir()


def test_full_disk_fails_one_sequence_and_leaves_no_temps(tmp_path, monkeypatch):
    import embody.store.artifacts as artifacts
    from embody.io import load_dataset

    refs = list(load_dataset(_write_amass(tmp_path / "data", n=3)))
    ctx = Context(cfg=Config(), store_root=str(tmp_path / "store"), run="r")
    real = artifacts.jsonable

    def full_for_seq001(value):
        if isinstance(value, dict) and value.get("embody", {}).get("sequence") == "seq001":
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(value)

    monkeypatch.setattr(artifacts, "jsonable", full_for_seq001)
    recs = _chain(ctx, refs, (SOURCE, COLLIDE))
    assert [r["status"] for r in recs] == ["ok", "failed", "ok"]
    assert "No space left" in recs[1]["error"] and recs[1]["failed_step"] == "source"
    leftovers = [p for p in (tmp_path / "store" / "artifacts").rglob("*") if ".tmp-" in p.name]
    assert leftovers == []


def test_full_disk_while_saving_the_manifest_leaves_no_temp(tmp_path, monkeypatch, capsys):
    store = ArtifactStore(tmp_path)
    m = Manifest(store, "r")
    m.start(["s1"])
    before = m.path.read_text()
    real = json.dumps

    def half_then_full(data, f, **kw):  # the manifest is streamed with json.dump
        text = real(data, **kw)
        f.write(text[: len(text) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(json, "dump", half_then_full)
    m.update({"id": "s1", "keys": {"collide": K1}, "status": "ok"})
    with pytest.raises(OSError):
        m.save(finished=True)
    monkeypatch.undo()
    assert m.path.read_text() == before  # the old manifest is intact
    assert list(m.path.parent.glob(".*.tmp")) == []
    # a temp left by a writer that died (here: a pid that does not exist) is gc's to remove
    stale = m.path.parent / f".manifest.json.{2 ** 22 + 7}.tmp"
    stale.write_text("{trunc")
    out = _gc(tmp_path, capsys)
    assert out["temps"] == [str(stale)] and not stale.exists()


def test_corrupt_manifest_is_one_line_for_ls_and_gc(tmp_path, capsys):
    (tmp_path / "runs" / "r").mkdir(parents=True)
    (tmp_path / "runs" / "r" / "manifest.json").write_text("{not json")
    for cmd in ("ls", "gc"):
        assert main(["store", cmd, "--store", str(tmp_path)]) == 2
        err = capsys.readouterr().err
        assert "manifest.json" in err and "Traceback" not in err


# -- config knowable up front (item 11) ------------------------------------------------------------
def test_bad_store_paths_fail_before_anything_is_created(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    data = _write_amass(tmp_path / "data")
    assert main(["run", str(data), "--store", "http://example.com/store"]) == 2
    assert "run.store" in capsys.readouterr().err
    assert not (tmp_path / "http:").exists()
    assert main(["run", str(data), "--store", str(tmp_path / "no" / "such" / "store")]) == 2
    assert "parent folder" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


def test_vlm_config_is_checked_before_the_run(tmp_path, monkeypatch, capsys):
    data = _write_amass(tmp_path / "data")
    store = tmp_path / "store"
    monkeypatch.delenv("EMBODY_VLM_API_KEY", raising=False)
    assert main(["run", str(data), "--store", str(store), "--critic", "vlm"]) == 2
    assert "EMBODY_VLM_API_KEY" in capsys.readouterr().err
    monkeypatch.setenv("EMBODY_VLM_API_KEY", "sk-inner\nnewline")
    assert main(["run", str(data), "--store", str(store), "--critic", "vlm"]) == 2
    err = capsys.readouterr().err
    assert "control" in err and "sk-inner" not in err
    monkeypatch.setenv("EMBODY_VLM_API_KEY", "sk-fine")
    assert main(["run", str(data), "--store", str(store), "--critic", "vlm",
                 "--set", "critic.vlm.base_url=file:///etc/passwd"]) == 2
    assert "critic.vlm.base_url" in capsys.readouterr().err
    assert not store.exists()


# -- run names: robot in the default, no silent reuse (issue 17 item 1) ------------------------------
def test_default_run_name_includes_the_robot():
    from embody.flows.dataset import default_run_name

    assert default_run_name(Path("x/synth-n24-s0"), None, "unitree_g1_dex3") == \
        "synth-n24-s0.unitree_g1_dex3"
    assert default_run_name(Path("soke"), "test", "unitree_h1") == "soke-test.unitree_h1"


def test_reusing_a_run_name_for_another_robot_is_refused(tmp_path, capsys):
    data = _write_amass(tmp_path / "data")
    store = ArtifactStore(tmp_path / "store")
    m = Manifest(store, "mine")
    m.start(["seq000"], dataset=str(data.resolve()), split=None,
            config=Config().model_dump(mode="json"))
    args = ["run", str(data), "--store", str(store.root), "--name", "mine"]
    assert main([*args, "--robot", "unitree_h1"]) == 2
    err = capsys.readouterr().err
    assert "unitree_g1_dex3" in err and "--overwrite" in err
    other = _write_amass(tmp_path / "other")
    assert main(["run", str(other), "--store", str(store.root), "--name", "mine"]) == 2
    assert "dataset" in capsys.readouterr().err
    assert json.loads(m.path.read_text())["sequences"] == {"seq000": m.sequences["seq000"]}
    from embody.flows.dataset import check_run_reuse

    check_run_reuse(store.root, "mine", data, None, "unitree_g1_dex3")  # same robot and data: ok
    check_run_reuse(store.root, "mine", other, None, "unitree_h1", overwrite=True)


def test_sequences_csv_cells_are_never_formulas(tmp_path):
    from embody.flows.dataset import write_tables

    store = ArtifactStore(tmp_path)
    m = Manifest(store, "r")
    m.start(["s1"])
    m.update({"id": "s1", "status": "failed", "error": "=HYPERLINK(\"http://x\")",
              "failed_step": "source", "metrics": {"source": {"note": "@SUM(A1)", "n": -3}}})
    text = write_tables(store, "r", m).read_text()
    row = pd.read_csv(tmp_path / "runs" / "r" / "sequences.csv").iloc[0]
    assert row["error"].startswith("'=") and row["source.note"] == "'@SUM(A1)"
    assert row["source.n"] == -3 and "\n=" not in text and ",=" not in text


# -- one run name, two datasets at once (issue 34 item 5) --------------------------------------------
_HOLD = """
import sys, time
from pathlib import Path
from embody.store.claims import claimed
with claimed(Path(sys.argv[1]), {"dataset": sys.argv[2], "split": None,
                                  "robot": "unitree_g1_dex3"}):
    print("claimed", flush=True)
    time.sleep(120)
"""


def test_a_live_run_of_the_name_over_other_data_refuses_the_second(tmp_path, capsys):
    """Run A (a real process holding its claim, as `embody run` does from before its first
    write to its exit) has not written its manifest yet; run B, same --name, another dataset,
    is refused with one line and writes nothing; same-data runs share the name; once A is gone
    the name is free."""
    import subprocess
    import sys

    from embody.store.claims import claimed

    a_data, b_data = _write_amass(tmp_path / "a"), _write_amass(tmp_path / "b")
    store = tmp_path / "store"
    run_dir = store.resolve() / "runs" / "shared"
    proc = subprocess.Popen([sys.executable, "-c", _HOLD, str(run_dir), str(a_data.resolve())],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "claimed"
        assert main(["run", str(b_data), "--store", str(store), "--name", "shared",
                     "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "'run.name'" in err, err
        assert str(a_data.resolve()) in err and f"pid {proc.pid}" in err
        assert not (run_dir / "manifest.json").exists() and not (store / "prefect").exists()
        with claimed(run_dir, {"dataset": str(a_data.resolve()), "split": None,
                               "robot": "unitree_g1_dex3"}):
            pass  # the same data shares the name, as before
        with pytest.raises(ConfigError, match="robot 'unitree_g1_dex3'"):
            with claimed(run_dir, {"dataset": str(a_data.resolve()), "split": None,
                                   "robot": "unitree_h1"}):
                pass
    finally:
        proc.kill()
        proc.wait()
    with claimed(run_dir, {"dataset": str(b_data.resolve()), "split": None,
                           "robot": "unitree_g1_dex3"}):
        pass  # A died: the kernel dropped its lock, the name is free
    claim = json.loads((store / "runs" / ".locks" / "shared.claim.json").read_text())
    assert claim["dataset"] == str(b_data.resolve())


def test_a_refused_dataset_leaves_nothing_in_the_store(tmp_path, monkeypatch, capsys):
    """Datasets refused when they are listed (exit 2): no store folder, no Prefect home."""
    monkeypatch.chdir(tmp_path)
    store = tmp_path / "store"
    empty = tmp_path / "empty"
    empty.mkdir()
    outside = tmp_path / "lists" / "list.csv"
    outside.parent.mkdir()
    outside.write_text("path,text\n../a/seq000.npz,hello\n")
    _write_amass(tmp_path / "a")
    for dataset in (empty, tmp_path / "missing", outside):
        assert main(["run", str(dataset), "--store", str(store), "--no-progress"]) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
        assert not store.exists(), sorted(str(p) for p in store.rglob("*"))
    store.mkdir()  # an existing store: still nothing added
    assert main(["run", str(empty), "--store", str(store), "--no-progress"]) == 2
    assert list(store.iterdir()) == []


def test_a_mistyped_embody_meta_fails_its_sequence_in_a_run_naming_the_field(tmp_path):
    """`run` no longer accepts `{"meta": {"artifacts": "xyz"}}` silently: the source step fails
    that sequence with the one-line error naming file and field; the others go on."""
    from embody.io import load_dataset

    data = _write_amass(tmp_path / "data")
    with np.load(data / "seq001.npz") as z:
        arrays = dict(z)
    np.savez(data / "seq001.npz", **arrays,
             embody_meta=np.array(json.dumps({"meta": {"artifacts": "xyz"}})))
    refs = list(load_dataset(data))
    ctx = Context(cfg=Config(), store_root=str(tmp_path / "store"), run="r")
    recs = _chain(ctx, refs, (SOURCE,))
    assert [r["status"] for r in recs] == ["ok", "failed"]
    assert "seq001.npz: field 'embody_meta.meta.artifacts'" in recs[1]["error"]
    assert len(recs[1]["error"].splitlines()) == 1
