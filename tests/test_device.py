"""`collision.device`: where the torch paths run. CI has no GPU, so on it `cuda` must fail as
a config error (exit 2) and `auto` must give the CPU's result bit for bit; on a machine with a
GPU the same tests check the CUDA result against the CPU's instead."""

from __future__ import annotations

import numpy as np
import pydantic
import pytest
import torch

from embody.body import MannequinBody
from embody.cli import main
from embody.collision import mitigate
from embody.config.collision import CollisionConfig
from embody.device import torch_device
from embody.errors import ConfigError
from embody.io import load, save
from tests.test_collision_optimize import colliding_motion

CUDA = torch.cuda.is_available()


def test_device_settings_resolve():
    assert torch_device("cpu") == torch.device("cpu")
    assert torch_device("auto").type == ("cuda" if CUDA else "cpu")
    with pytest.raises(ConfigError, match="x.device.*unknown device 'tpu'"):
        torch_device("tpu", "x.device")
    with pytest.raises(pydantic.ValidationError):
        CollisionConfig(device="tpu")


def test_cuda_without_a_gpu_is_a_config_error_else_matches_the_cpu():
    body, motion = MannequinBody(), colliding_motion(8)
    cfg = CollisionConfig(steps=60)
    cpu = mitigate(motion, body, cfg)
    if not CUDA:
        with pytest.raises(ConfigError, match="collision.device.*no CUDA device"):
            mitigate(motion, body, cfg.model_copy(update={"device": "cuda"}))
        auto = mitigate(motion, body, cfg.model_copy(update={"device": "auto"}))
        assert np.array_equal(auto.motion.pose, cpu.motion.pose)
        return
    gpu = mitigate(motion, body, cfg.model_copy(update={"device": "cuda"}))
    assert gpu.metrics["energy_after"] <= 0.05 * gpu.metrics["energy_before"]
    assert gpu.metrics["max_depth_mm_after"] <= cpu.metrics["max_depth_mm_after"] + 0.5
    assert np.abs(gpu.motion.pose - cpu.motion.pose).max() < 0.05  # float32 rounding paths differ


def test_cli_names_the_device_setting(tmp_path, capsys):
    src, dst = tmp_path / "in.npz", tmp_path / "out.npz"
    save(colliding_motion(6), src)
    code = main(["collide", str(src), str(dst), "--set", "collision.steps=30",
                 "--set", "collision.device=cuda"])
    if CUDA:
        assert code == 0 and load(dst).num_frames == 6
        return
    assert code == 2
    assert "collision.device" in capsys.readouterr().err
    assert not dst.exists()
