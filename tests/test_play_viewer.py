"""`embody play --viewer`: MuJoCo's interactive viewer needs a display; without one the command
says so in one line and exits 2 (bad usage), before loading anything."""

from __future__ import annotations

from embody.cli import main
from embody.cli.play import has_display


def test_viewer_without_display_exits_2_with_a_clear_message(monkeypatch, tmp_path, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    assert not has_display()
    traj = tmp_path / "seq.npz"
    traj.write_bytes(b"not read: the display is checked first")
    assert main(["play", str(traj), "--viewer"]) == 2
    err = capsys.readouterr().err
    assert "--viewer needs a display" in err and "DISPLAY" in err
    assert len(err.strip().splitlines()) == 1
    assert not list(tmp_path.glob("seq.*[!z]"))  # no preview written


def test_display_detection(monkeypatch):
    monkeypatch.setattr("sys.platform", "linux")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setenv("DISPLAY", ":0")
    assert has_display()
    monkeypatch.delenv("DISPLAY")
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    assert has_display()
