"""A real `prefect server start`: `embody run` against it, and `embody serve` firing on schedule.

Slow (a server start with migrations, a wait of up to a minute for the cron schedule) but run in
CI: schedules only fire on a persistent server, and nothing else exercises that path.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from embody.flows.server import LocalServer

ROOT = Path(__file__).resolve().parents[1]
EMBODY = [sys.executable, "-c", "import sys; from embody.cli import main; sys.exit(main())"]
CHEAP = ["--critic", "none", "--no-render", "--workers", "1",
         "--set", "collision.enabled=false", "--set", "ik.iterations=1",
         "--set", "ik.shape_iterations=10", "--set", "run.report=false"]


def _write(folder: Path, n: int = 2, frames: int = 4) -> Path:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(5)
    for i in range(n):
        np.savez(folder / f"seq{i:03d}.npz", poses=rng.normal(0, 0.1, (frames, 165)),
                 trans=np.zeros((frames, 3)), betas=np.zeros(10), gender="neutral",
                 mocap_frame_rate=30.0)
    return folder


def _flow_runs(api: str) -> list[dict]:
    import httpx
    return httpx.post(api + "/flow_runs/filter", json={}, timeout=30).json()


def _next_minute_cron(margin_s: float = 15.0) -> tuple[str, dt.datetime]:
    """A daily cron (UTC) at the first whole minute at least `margin_s` from now."""
    t = dt.datetime.now(dt.timezone.utc) + dt.timedelta(seconds=margin_s)
    t = t.replace(second=0, microsecond=0) + dt.timedelta(minutes=1)
    return f"{t.minute} {t.hour} * * *", t


@pytest.mark.slow
def test_run_and_a_scheduled_serve_on_a_real_prefect_server(tmp_path):
    data = _write(tmp_path / "data")
    server = LocalServer(tmp_path / "prefect-home")
    serve: subprocess.Popen | None = None
    try:
        api = server.start()
        env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
        env.update(PREFECT_API_URL=api, PYTHONPATH=str(ROOT), DO_NOT_TRACK="1",
                   PREFECT_SERVER_ANALYTICS_ENABLED="false")
        # The scheduled run waits for a whole minute: serve first, and do the direct run
        # while that minute comes.
        cron, due = _next_minute_cron()
        manifest = tmp_path / "served" / "runs" / "nightly" / "manifest.json"
        serve = subprocess.Popen(
            [*EMBODY, "serve", "--cron", cron, str(data), "--store", str(tmp_path / "served"),
             "--name", "nightly", *CHEAP], env=env, cwd=tmp_path, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True, start_new_session=True)
        run = subprocess.run([*EMBODY, "run", str(data), "--store", str(tmp_path / "store"),
                              "--name", "direct", "--json", "--no-progress", *CHEAP],
                             env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr[-3000:]
        assert json.loads(run.stdout)["ok"] == 2
        # The run went through this server, not an ephemeral one of its own.
        assert [(r["flow_id"] is not None, r["state_type"]) for r in _flow_runs(api)
                if r["deployment_id"] is None] == [(True, "COMPLETED")]
        assert not (tmp_path / "store" / "prefect").exists() or \
            not any((tmp_path / "store" / "prefect").glob("*.db"))

        # 240 s for the scheduled run from when it is due, or from now if the direct run
        # took longer than the wait
        deadline = max(due, dt.datetime.now(dt.timezone.utc)) + dt.timedelta(seconds=240)
        finished = None
        while dt.datetime.now(dt.timezone.utc) < deadline and serve.poll() is None:
            if manifest.is_file():
                doc = json.loads(manifest.read_text())
                if doc.get("finished"):
                    finished = doc
                    break
            time.sleep(1)
        assert serve.poll() is None, serve.stdout.read()[-3000:]
        assert finished is not None, f"the scheduled run at {due} did not finish"
        assert {s["status"] for s in finished["sequences"].values()} == {"ok"}
        assert len(finished["sequences"]) == 2
        assert dt.datetime.now(dt.timezone.utc) >= due  # it ran on schedule, not at once
        scheduled = [r for r in _flow_runs(api) if r["deployment_id"] is not None
                     and r["state_type"] in ("RUNNING", "COMPLETED")]
        assert len(scheduled) == 1
        assert abs(dt.datetime.fromisoformat(scheduled[0]["expected_start_time"]
                                             .replace("Z", "+00:00")) - due) < dt.timedelta(seconds=1)
    finally:
        if serve is not None and serve.poll() is None:
            os.killpg(serve.pid, signal.SIGINT)  # Ctrl-C: the runner cancels and exits
            try:
                serve.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(serve.pid, signal.SIGKILL)
                serve.wait()
        server.stop()
    assert server.proc is not None and server.proc.poll() is not None
