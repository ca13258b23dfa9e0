"""The refinement loop: the geometric critic undoes an offset planted on the IK targets; the VLM
critic runs end to end against a local server without leaking its key; the CLI writes its files."""

import dataclasses
import json
import logging
import os

import numpy as np
import pytest
import torch

from embody.cli import main
from embody.config import load_config
from embody.config.critic import CriticConfig, VLMConfig
from embody.config.ik import IKConfig
from embody.config.render import RenderConfig
from embody.critic import RefineResult, VLMCritic, refine, refine_table
from embody.critic.vlm import VLMClient
from embody.motion import Motion
from embody.retarget import build_targets, shape_fit, solve
from embody.retarget.targets import Targets, robot_arm_length
from embody.robot import load_robot

from test_vlm import SENTINEL, FakeServer

FPS = 30.0
IK = IKConfig(iterations=60)
RENDER = RenderConfig(width=64, height=48, keyframes=2, preview_format="gif", preview_fps=4)


@pytest.fixture(scope="module")
def robot():
    return load_robot()


def _reachable_targets(robot, t: int) -> Targets:
    """Targets the robot can reach exactly: FK of a smooth arm motion in front of the chest."""
    q = np.tile(robot.tpose, (t, 1))
    s = np.linspace(0, 1, t)
    for side, sign in (("left", 1), ("right", -1)):
        q[:, robot.joint_index(f"{side}_shoulder_roll_joint")] = sign * (0.3 + 0.2 * s)
        q[:, robot.joint_index(f"{side}_shoulder_pitch_joint")] = -0.6 - 0.3 * np.sin(np.pi * s)
        q[:, robot.joint_index(f"{side}_elbow_joint")] = 0.6
    q = robot.clip(q)
    with torch.no_grad():
        p, r = robot.link_points(torch.tensor(q), ["left_wrist", "right_wrist", "left_elbow", "right_elbow"])
    eye = np.tile(np.eye(3), (t, 1, 1))
    return Targets(wrist_pos=p[:, :2].numpy(), wrist_rot=r[:, :2].numpy(), elbow_pos=p[:, 2:].numpy(),
                   torso_rot=eye, head_rot=eye, hand_q=np.zeros((t, 0)), hand_joints=[], fps=FPS,
                   arm_length=robot_arm_length(robot))


def _motion(t: int) -> Motion:
    pose = np.zeros((t, 55, 3), np.float32)
    s = np.linspace(0, 1, t)
    pose[:, 16, 2], pose[:, 17, 2] = -1.0 + 0.2 * s, 1.0
    pose[:, 18, 1], pose[:, 19, 1] = -1.9, 1.9 - 0.3 * s
    return Motion(pose=pose, transl=np.zeros((t, 3)), betas=np.zeros(10), fps=FPS, meta={"text": "test"})


def _wrist_error_mm(robot, q, targets):
    with torch.no_grad():
        p, _ = robot.link_points(torch.tensor(q), ["left_wrist", "right_wrist"])
    return float(np.linalg.norm(p.numpy() - targets.wrist_pos, axis=-1).mean() * 1000)


def test_geometric_critic_recovers_a_planted_10cm_offset(robot):
    reference = _reachable_targets(robot, 10)
    planted = reference.wrist_pos.copy()
    planted[:, 0, 2] += 0.10  # the IK was given a left target 10 cm too high
    ik_targets = dataclasses.replace(reference, wrist_pos=planted)
    ik_only = solve(robot, ik_targets, IK)
    assert _wrist_error_mm(robot, ik_only.q, reference) > 35  # both wrists pooled: ≈ 50 mm

    result = refine(_motion(10), None, None, robot, reference, ik_only, CriticConfig(rounds=2), IK,
                    RENDER, ik_targets=ik_targets)
    assert 2 <= len(result.rounds) <= 3
    first = {p["name"]: p["amount"] for p in result.rounds[0].action["primitives_positions"]}
    assert 0.08 <= first["move_left_down"] <= 0.10  # the IK-only solution nearly reached the plant
    final = result.final
    assert _wrist_error_mm(robot, final.q, reference) < 20.0
    assert final.metrics["wrist_mm_mean"] < 20.0 < result.ik_only.metrics["wrist_mm_mean"]
    # the reference never moves; the working targets of the last round are back near it
    assert np.abs(final.target_pos[:, 0, 2] - reference.wrist_pos[:, 0, 2]).max() < 0.03

    back = RefineResult.from_arrays(result.to_arrays(), json.loads(json.dumps(result.to_attrs())))
    assert np.array_equal(back.q, result.q) and back.to_attrs() == result.to_attrs()
    table = refine_table({"a": result})
    assert list(table.index) == ["IK-only", "refined"]
    assert table.loc["refined", "wrist_mm_mean"] < table.loc["IK-only", "wrist_mm_mean"]


def test_keep_policy_picks_the_result_round(robot):
    """A revision that moves the wrists away from the reference is not kept by `best` (the
    geometric default), and is kept by `last` (a VLM's call)."""
    from embody.critic.base import Critic
    from embody.critic.action import Action

    class AlwaysUp(Critic):
        needs_images = False

        def critique(self, context):
            return Action.parse({"primitives_positions": ["move_left_up"],
                                 "primitives_orientation": [], "verdict": "revise",
                                 "reason": "test"}, context.limits)

    reference = _reachable_targets(robot, 10)
    ik_only = solve(robot, reference, IK)
    results = {keep: refine(_motion(10), None, None, robot, reference, ik_only,
                            CriticConfig(rounds=1, keep=keep), IK, RENDER, critic=AlwaysUp())
               for keep in ("auto", "last")}
    best, last = results["auto"], results["last"]
    assert len(best.rounds) == len(last.rounds) == 2
    assert best.final.index == 0 and last.final.index == 1
    assert best.final.metrics["wrist_mm_mean"] < last.final.metrics["wrist_mm_mean"]
    assert np.array_equal(best.q, ik_only.q)
    back = RefineResult.from_arrays(best.to_arrays(), json.loads(json.dumps(best.to_attrs())))
    assert back.final.index == 0
    table = refine_table([best])
    assert table.loc["refined", "rounds"] == 1.0  # rounds run, not the index of the kept one


@pytest.fixture(scope="module")
def body_fit(robot):
    from embody.body import load_body_model

    body = load_body_model()
    return body, shape_fit(robot, body, IKConfig(shape_iterations=40), use_cache=False)


def test_vlm_refinement_end_to_end_never_leaks_the_key(robot, body_fit, tmp_path, monkeypatch, caplog):
    caplog.set_level(logging.DEBUG)
    monkeypatch.setenv("EMBODY_VLM_API_KEY", SENTINEL)
    body, fit = body_fit
    motion = _motion(8)
    targets = build_targets(motion, body, fit, robot)
    sol = solve(robot, targets, IKConfig(iterations=15))
    server = FakeServer()
    try:
        server.reply(json.dumps({"primitives_positions": ["move_left_up"], "primitives_orientation": [],
                                 "verdict": "revise", "reason": f"left low {SENTINEL}"}))
        cfg = VLMConfig(base_url=server.url, timeout_s=5, max_retries=0)
        result = refine(motion, body, fit, robot, targets, sol,
                        CriticConfig(kind="vlm", rounds=1, vlm=cfg), IKConfig(iterations=15), RENDER,
                        out_dir=tmp_path, critic=VLMCritic(cfg, VLMClient(cfg)))
    finally:
        server.close()
    assert len(server.requests) == 1 and len(result.rounds) == 2
    r0 = result.rounds[0]
    assert r0.action["primitives_positions"][0]["name"] == "move_left_up"
    # the round's images are stored by hash, and they are the files written
    from embody.critic.vlm import sha256

    sheet = r0.renders["sheet"]
    assert sha256((tmp_path / sheet["path"]).read_bytes()) == sheet["sha256"]
    assert sheet["sha256"] in json.dumps(r0.exchange["request"])
    assert (tmp_path / "sheet.png").is_file() and (tmp_path / "preview.gif").is_file()
    np.testing.assert_allclose(result.final.target_pos[:, 0, 2] - targets.wrist_pos[:, 0, 2], 0.10)
    # the sentinel appears nowhere: files, records, logs
    for path in tmp_path.rglob("*"):
        if path.is_file():
            assert SENTINEL.encode() not in path.read_bytes(), path
    assert SENTINEL not in json.dumps(result.to_attrs())
    assert all(SENTINEL not in r.getMessage() for r in caplog.records)


def test_cli_refine_writes_sheet_and_npz(tmp_path, monkeypatch, capsys):
    from embody.io import save

    monkeypatch.setenv("EMBODY_CACHE", str(tmp_path / "cache"))
    src = tmp_path / "m.npz"
    save(_motion(6), src)
    out = tmp_path / "out"
    sets = ["--set", "ik.iterations=10", "--set", "ik.shape_iterations=20", "--set", "render.width=64",
            "--set", "render.height=48", "--set", "render.keyframes=2", "--set", "render.preview_format=none",
            "--set", "critic.rounds=1"]
    code = main(["refine", str(src), str(out), "--critic", "geometric", "--json", *sets])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert {"sheet.png", "refine.npz"} <= set(report["files"])
    with np.load(out / "refine.npz") as z:
        attrs = json.loads(str(z["attrs"]))
        assert z["q"].shape[0] == len(attrs["rounds"]) == report["rounds"]
    assert set(report["table"]) == {"IK-only", "refined"}
    assert main(["refine", str(tmp_path / "missing.npz"), str(out)]) == 2
    monkeypatch.delenv("EMBODY_VLM_API_KEY", raising=False)
    assert main(["refine", str(src), str(out), "--critic", "vlm"]) == 2  # no key: bad config
    assert "EMBODY_VLM_API_KEY" in capsys.readouterr().err
    assert not os.environ.get("EMBODY_VLM_API_KEY")
    load_config()  # the default config still validates
