"""Up axis and hands detected from the data, as a check on what the keys claim (issue 36: a
BEAT2 file without its `model` key was read as z-up with absolute hands, silently).

Fixtures are built here: a y-up body (root orientation near identity, swaying) with relaxed
fingers varying around the SMPL-X hand mean, stored in each layout."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from embody.cli import main
from embody.io import hand_mean, load
from embody.io.conventions import layout_warnings
from embody.io.frames import Z_UP_TO_Y_UP, rotate_root
from embody.io.layout import detect_hands, detect_up_axis

T = 40


def _motion(seed: int = 0, curl: tuple[float, float] = (0.6, 1.4)) -> tuple[np.ndarray, np.ndarray]:
    """(T,55,3) y-up pose with absolute hands, and (T,3) translation."""
    rng = np.random.default_rng(seed)
    pose = np.zeros((T, 55, 3))
    sway = Rotation.from_euler("yx", np.stack([rng.uniform(-25, 25, T), rng.uniform(-8, 8, T)], 1),
                               degrees=True)
    pose[:, 0] = sway.as_rotvec()
    pose[:, 1:22] = rng.normal(0, 0.1, (T, 21, 3))
    pose[:, 25:55] = hand_mean() * rng.uniform(*curl, (T, 1, 1)) + rng.normal(0, 0.04, (T, 30, 3))
    transl = np.tile([0.0, 0.95, 0.0], (T, 1)) + rng.normal(0, 0.01, (T, 3))
    return pose, transl


def _beat2(path, pose, transl, model: bool) -> None:
    """BEAT2 layout: y-up, mean-relative hands, AMASS's frame-rate key, `model` optional."""
    rel = pose.copy()
    rel[:, 25:55] -= hand_mean()
    extra = {"model": np.array("smplx2020")} if model else {}
    np.savez(path, poses=rel.reshape(T, 165), trans=transl, betas=np.zeros(300),
             gender=np.array("neutral"), mocap_frame_rate=np.array(30), **extra)


def test_beat2_without_model_is_warned_about_with_the_overrides_that_settle_it(tmp_path, capsys):
    pose, transl = _motion()
    _beat2(tmp_path / "keyed.npz", pose, transl, model=True)
    _beat2(tmp_path / "bare.npz", pose, transl, model=False)
    keyed = load(tmp_path / "keyed.npz")
    assert layout_warnings(keyed.source.provenance) == []  # keys and data agree
    check = keyed.source.provenance["check"]
    assert check["up_axis"]["data"] == "y" and check["hands"]["data"] == "relative"

    bare = load(tmp_path / "bare.npz")
    check = bare.source.provenance["check"]
    assert bare.source.provenance["up_axis"]["value"] == "z"  # what the keys say, kept
    assert check["up_axis"]["data"] == "y" and check["hands"]["data"] == "relative"
    warnings = layout_warnings(bare.source.provenance)
    assert len(warnings) == 2
    assert "--up-axis y" in warnings[0] and "'z'" in warnings[0]
    assert "--hands relative" in warnings[1] and "'absolute'" in warnings[1]

    # the overrides the warnings name settle it: the same motion as the keyed file, no warning
    settled = load(tmp_path / "bare.npz", up_axis="y", hands="relative")
    assert layout_warnings(settled.source.provenance) == []
    np.testing.assert_allclose(settled.pose, keyed.pose, atol=1e-6)
    np.testing.assert_allclose(settled.transl, keyed.transl, atol=1e-6)

    # inspect says it once, on stderr, with the overrides; --json carries it too
    assert main(["inspect", str(tmp_path / "bare.npz")]) == 0
    err = capsys.readouterr().err
    assert err.count("warning:") == 2 and "--up-axis y" in err and "--hands relative" in err
    assert main(["inspect", str(tmp_path / "bare.npz"), "--json"]) == 0
    out = capsys.readouterr()
    assert json.loads(out.out)["provenance"]["check"]["up_axis"]["data"] == "y"
    assert out.err.count("warning:") == 2
    assert main(["inspect", str(tmp_path / "bare.npz"), "--up-axis", "y", "--hands", "relative"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_amass_layout_z_up_absolute_passes_the_check(tmp_path):
    pose, transl = _motion(1)
    zpose, ztransl = rotate_root(pose, transl, Z_UP_TO_Y_UP.T)  # y-up → z-up
    np.savez(tmp_path / "a.npz", poses=zpose.reshape(T, 165), trans=ztransl,
             mocap_frame_rate=np.array(120.0))
    m = load(tmp_path / "a.npz")
    check = m.source.provenance["check"]
    assert check["up_axis"]["data"] == "z" and check["hands"]["data"] == "absolute"
    assert layout_warnings(m.source.provenance) == []
    np.testing.assert_allclose(m.pose, pose, atol=1e-5)  # back to y-up as built


def test_ambiguous_hands_under_a_default_are_warned_about(tmp_path):
    """Flat-handed absolute signing looks like relaxed relative hands: the data cannot tell,
    and the AMASS default is only a default, so the warning names both choices."""
    pose, transl = _motion(2, curl=(0.0, 0.3))
    zpose, ztransl = rotate_root(pose, transl, Z_UP_TO_Y_UP.T)
    np.savez(tmp_path / "f.npz", poses=zpose.reshape(T, 165), trans=ztransl,
             mocap_frame_rate=np.array(30.0))
    m = load(tmp_path / "f.npz")
    assert m.source.provenance["check"]["hands"]["data"] is None
    (warning,) = layout_warnings(m.source.provenance)
    assert "cannot confirm" in warning and "--hands absolute|relative" in warning


def test_detectors_on_every_axis_and_no_evidence():
    pose, _ = _motion(3)
    base = Rotation.from_rotvec(pose[:, 0])
    for axis, turn in (("y", Rotation.identity()), ("z", Rotation.from_euler("x", 90, degrees=True)),
                       ("camera", Rotation.from_euler("x", 180, degrees=True))):
        assert detect_up_axis((turn * base).as_rotvec()).value == axis
    lying = Rotation.from_euler("x", -90, degrees=True) * base  # on its face in a y-up world
    assert detect_up_axis(lying.as_rotvec()).value is None
    assert detect_up_axis(np.zeros((T, 3))) is None  # no root rotation: no evidence
    assert detect_hands(np.zeros((T, 55, 3))) is None
    rel = pose.copy()
    rel[:, 25:55] -= hand_mean()
    assert detect_hands(pose).value == "absolute" and detect_hands(rel).value == "relative"


def test_embody_files_are_not_rejudged(tmp_path):
    from embody.io import save

    pose, transl = _motion(4, curl=(0.0, 0.2))
    np.savez(tmp_path / "y.npz", poses=pose.reshape(T, 165), trans=transl, model=np.array("smplx2020"),
             mocap_frame_rate=np.array(30), betas=np.zeros(10))
    m = load(tmp_path / "y.npz", hands="absolute")
    back = load(save(m, tmp_path / "own.npz"))
    assert "check" not in back.source.provenance


def test_run_summary_names_each_layout_warning_once(tmp_path):
    """The source step's metrics carry a clip's warnings; the run's closing summary groups the
    same warning over every sequence it concerns (said once, not once per file)."""
    from types import SimpleNamespace

    from embody.flows.verdicts import layout_warnings as run_warnings, verdict_summary
    from embody.tasks.stages import SOURCE

    pose, transl = _motion(5)
    sequences = {}
    for sid in ("a", "b"):
        _beat2(tmp_path / f"{sid}.npz", pose, transl, model=False)
        sequences[sid] = {"status": "ok", "metrics": {"source": SOURCE.metrics(load(tmp_path / f"{sid}.npz"))}}
    _beat2(tmp_path / "c.npz", pose, transl, model=True)
    sequences["c"] = {"status": "ok", "metrics": {"source": SOURCE.metrics(load(tmp_path / "c.npz"))}}
    assert "layout_warnings" not in sequences["c"]["metrics"]["source"]
    manifest = SimpleNamespace(sequences=sequences)
    grouped = run_warnings(manifest)
    assert [(g["count"], g["ids"]) for g in grouped] == [(2, ["a", "b"]), (2, ["a", "b"])]
    assert "--up-axis y" in grouped[0]["warning"] and "--hands relative" in grouped[1]["warning"]
    assert verdict_summary(manifest)["layout_warnings"] == grouped


def test_the_same_finding_on_two_clips_is_one_warning(tmp_path):
    """Warnings name no clip and no measurement, so a run over many clips says each once."""
    texts = set()
    for seed in (6, 7):
        pose, transl = _motion(seed)
        _beat2(tmp_path / f"{seed}.npz", pose, transl, model=False)
        texts |= set(layout_warnings(load(tmp_path / f"{seed}.npz").source.provenance))
    assert len(texts) == 2
