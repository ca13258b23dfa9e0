"""Hostile or broken runs (issue 10) through the real flow: the VLM key never leaks, corrupt
artifacts are recomputed and reported, a full disk ends with a summary, killed runs leave no
Prefect server behind."""

from __future__ import annotations

import errno
import json
import os
import pathlib
import signal
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from embody.cli import main
from embody.store import ArtifactStore, Manifest

SECRET = "sk-LEAKCHECK-4b1d9e-do-not-leak"


class Endpoint:
    """A real HTTP server on 127.0.0.1: `redirect_to` answers 307 there, else a 200 reply."""

    def __init__(self, redirect_to: str | None = None):
        self.requests: list[dict] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 - http.server API
                self.rfile.read(int(self.headers.get("Content-Length", 0)))
                outer.requests.append({"path": self.path, "headers": dict(self.headers)})
                if redirect_to:
                    self.send_response(307)
                    self.send_header("Location", redirect_to + self.path)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                body = json.dumps({"choices": [{"message": {"content": json.dumps(
                    {"primitives_positions": [], "primitives_orientation": [],
                     "verdict": "accept", "reason": "ok"})}}]}).encode()
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()
        self.origin = f"http://127.0.0.1:{self.httpd.server_address[1]}"

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def test_client_strips_the_key_and_refuses_redirects(monkeypatch):
    from embody.config.critic import VLMConfig
    from embody.critic.vlm import VLMClient, VLMError

    target, hop = Endpoint(), None
    try:
        hop = Endpoint(redirect_to=target.origin)
        monkeypatch.setenv("EMBODY_VLM_API_KEY", SECRET + "\n")  # as read from a secret file
        ok = VLMClient(VLMConfig(base_url=target.origin + "/v1", max_retries=0))
        reply, _ = ok.chat({"model": "m", "messages": []})
        assert reply["choices"]
        assert target.requests[-1]["headers"]["Authorization"] == f"Bearer {SECRET}"
        n = len(target.requests)
        client = VLMClient(VLMConfig(base_url=hop.origin + "/v1", max_retries=0))
        with pytest.raises(VLMError, match="redirect") as exc:
            client.chat({"model": "m", "messages": []})
        assert SECRET not in str(exc.value)
        assert len(hop.requests) == 1 and len(target.requests) == n  # never followed
    finally:
        target.close()
        if hop:
            hop.close()


#: The real steps, made cheap (as tests/test_cli_run.py).
CHEAP = ["--set", "collision.enabled=false", "--set", "ik.iterations=1",
         "--set", "ik.shape_iterations=10", "--set", "critic.rounds=1",
         "--set", "render.width=64", "--set", "render.height=48", "--set", "render.keyframes=2",
         "--set", "render.preview_format=gif", "--set", "render.preview_max_frames=2"]


def test_vlm_key_never_reaches_manifest_tables_report_or_stderr(prefect_harness, tmp_path,
                                                                 monkeypatch, capsys):
    from toy_flow import write_amass

    monkeypatch.chdir(tmp_path)
    data = write_amass(tmp_path / "data", 1, frames=4)
    other_host = Endpoint()  # another port: where the redirect points
    hop = Endpoint(redirect_to=other_host.origin)
    try:
        monkeypatch.setenv("EMBODY_VLM_API_KEY", SECRET + "\n")
        code = main(["run", str(data), "--store", str(tmp_path / "store"), "--name", "vlm",
                     "--critic", "vlm", "--set", f"critic.vlm.base_url={hop.origin}/v1",
                     "--set", "critic.vlm.max_retries=0", *CHEAP])
        out = capsys.readouterr()
    finally:
        hop.close()
        other_host.close()
    assert code == 1, out.err
    assert hop.requests and hop.requests[0]["headers"]["Authorization"] == f"Bearer {SECRET}"
    assert other_host.requests == []  # the key never travelled to the redirect target
    run_dir = tmp_path / "store" / "runs" / "vlm"
    manifest = (run_dir / "manifest.json").read_text()
    assert "redirect" in manifest
    texts = {"manifest": manifest, "sequences.csv": (run_dir / "sequences.csv").read_text(),
             "stderr": out.err, "stdout": out.out}
    for path in (tmp_path / "reports" / "vlm").rglob("*"):
        if path.is_file() and path.suffix in (".html", ".csv", ".json", ".md"):
            texts[str(path)] = path.read_text()
    assert any(name.endswith("index.html") for name in texts)
    for name, text in texts.items():
        assert SECRET not in text, name


# -- corrupt artifacts and a full disk on the toy pipeline ---------------------------------------------
@pytest.fixture
def toy(tmp_path, monkeypatch):
    from toy_flow import write_amass

    monkeypatch.chdir(tmp_path)
    return write_amass(tmp_path / "data", 3)


def _flow(data, store: Path):
    from embody.flows.dataset import run_flow
    from test_flow import TOY, _cfg

    return run_flow(data, _cfg(store), pipeline=TOY)


def test_a_corrupt_artifact_is_recomputed_and_the_run_says_so(prefect_harness, toy, tmp_path):
    store = ArtifactStore(tmp_path / "store")
    first = _flow(toy, store.root)
    assert first["ok"] == 3 and first["recovered"] == []
    key = Manifest.load(store, "toy").sequences["seq001"]["steps"]["collide"]
    chunk = next(p for p in store.path("collide", key).rglob("*")
                 if p.is_file() and p.name != "zarr.json")
    chunk.unlink()  # zarr would hand out its fill value (zeros) for the pose
    again = _flow(toy, store.root)
    assert again["ok"] == 3
    assert again["computed"]["collide"] == 1
    assert [r["id"] for r in again["recovered"]] == ["seq001"]
    assert "collide/" in again["recovered"][0]["artifact"]
    assert store.verify("collide", key) is None
    assert Manifest.load(store, "toy").sequences["seq001"]["recovered"]


def test_full_disk_at_the_end_gives_a_summary_not_a_traceback(prefect_harness, toy, tmp_path,
                                                              monkeypatch):
    import embody.store.manifest as manifest_module
    real = json.dump

    def full_when_finishing(data, f, **kw):  # the manifest is streamed with json.dump
        if isinstance(data, dict) and "sequences" in data and data.get("finished") is not None:
            text = json.dumps(data, **kw)
            f.write(text[:10])
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(data, f, **kw)

    monkeypatch.setattr(manifest_module.json, "dump", full_when_finishing)
    summary = _flow(toy, tmp_path / "store")
    monkeypatch.undo()
    assert summary["errors"] and "no space left" in summary["errors"][0]
    assert summary["ok"] == 3 and summary["table"] is None
    run_dir = tmp_path / "store" / "runs" / "toy"
    assert list(run_dir.glob(".*.tmp")) == []
    assert json.loads((run_dir / "manifest.json").read_text())["finished"] is None


# -- killed runs and the ephemeral Prefect server -------------------------------------------------------
_RUN = """
import sys
sys.path.insert(0, sys.argv[1])
from embody.flows.env import configure, on_sigterm
configure(sys.argv[3])
on_sigterm()
from test_flow import TOY, _cfg
from embody.flows.dataset import run_flow
from pathlib import Path
run_flow(sys.argv[2], _cfg(Path(sys.argv[3]), workers=1, batch_size=1), pipeline=TOY)
"""


def _alive(pid: int) -> bool:
    from embody.store.artifacts import pid_alive as alive
    return alive(pid)


def _start(data: Path, store: Path) -> tuple[subprocess.Popen, int, Path]:
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_HOME")}
    env.update(TOY_SLOW="1.0", PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-c", _RUN, str(Path(__file__).parent), str(data),
                             str(store)], env=env, stderr=subprocess.PIPE, text=True)
    folder = store / "prefect" / "embody-servers"
    deadline = time.monotonic() + 150
    while time.monotonic() < deadline:
        files = list(folder.glob("*.json")) if folder.is_dir() else []
        if files:
            return proc, json.loads(files[0].read_text())["server"], files[0]
        assert proc.poll() is None, proc.stderr.read()
        time.sleep(0.1)
    proc.kill()
    raise AssertionError("the run never started its Prefect server")


def test_sigterm_stops_the_prefect_server(toy, tmp_path):
    proc, server, pidfile = _start(toy, tmp_path / "store")
    assert _alive(server)
    os.kill(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    deadline = time.monotonic() + 10
    while _alive(server) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = _alive(server)
    if alive:
        os.kill(server, signal.SIGKILL)
    assert not alive, "SIGTERM left the Prefect server running"
    assert not pidfile.exists()


def _process(*argv: str, home: Path) -> subprocess.Popen:
    env = dict(os.environ, PREFECT_HOME=str(home))
    return subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)", *argv], env=env)


def test_the_next_run_stops_servers_orphaned_by_sigkill(tmp_path, monkeypatch, capsys):
    """What a SIGKILLed run leaves: its pidfile and a live server whose owner is gone. The
    server here is a process with a Prefect server's command line under the store's home."""
    from embody.flows.env import configure

    store = tmp_path / "store"
    home = (store / "prefect").resolve()
    folder = home / "embody-servers"
    folder.mkdir(parents=True)
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # a dead owner
    server_args = ("-m", "uvicorn", "--factory", "prefect.server.api.server:create_app")
    orphan = _process(*server_args, home=home)
    owned = _process(*server_args, home=home)  # its run is still alive (this process)
    stranger = _process("not-a-server", home=home)  # pid reuse: not a Prefect server
    procs = (orphan, owned, stranger)
    try:
        for proc, owner in ((orphan, gone.pid), (owned, os.getpid()), (stranger, gone.pid)):
            (folder / f"{proc.pid}.json").write_text(json.dumps(
                {"server": proc.pid, "owner": owner, "home": str(home)}))
        time.sleep(0.3)  # let each exec so /proc shows its command line
        monkeypatch.setenv("PREFECT_HOME", str(home))
        configure(store)  # the first thing every run does
        assert f"pid {orphan.pid}" in capsys.readouterr().err
        assert orphan.wait(timeout=10) is not None
        assert owned.poll() is None and stranger.poll() is None
        assert sorted(p.name for p in folder.iterdir()) == [f"{owned.pid}.json"]
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


class Trickle:
    """A real HTTP server whose every answer is one byte every 0.2 s, forever."""

    def __init__(self):
        self.requests = 0
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 - http.server API
                self.rfile.read(int(self.headers.get("Content-Length", 0)))
                outer.requests += 1
                try:
                    self.send_response(200)
                    self.send_header("Content-Length", "1000000")
                    self.end_headers()
                    while True:
                        self.wfile.write(b" ")
                        self.wfile.flush()
                        time.sleep(0.2)
                except OSError:
                    pass

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()
        self.origin = f"http://127.0.0.1:{self.httpd.server_address[1]}"

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


def test_sigterm_ends_a_run_waiting_on_a_trickling_vlm(tmp_path):
    """`critic.vlm.timeout_s` of 10 minutes, a server that never finishes: one SIGTERM ends
    the run (exit 130: interrupted) and its Prefect server, well before the timeout."""
    from toy_flow import write_amass

    data = write_amass(tmp_path / "data", 1, frames=4)
    store = tmp_path / "store"
    vlm = Trickle()
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_HOME")}
    env.update(PYTHONPATH=os.pathsep.join(sys.path), EMBODY_VLM_API_KEY="k")
    proc = subprocess.Popen(
        [sys.executable, "-c", "import sys; from embody.cli import main; sys.exit(main())",
         "run", str(data), "--store", str(store), "--name", "slow", "--critic", "vlm",
         "--no-progress", "--set", f"critic.vlm.base_url={vlm.origin}/v1",
         "--set", "critic.vlm.timeout_s=600", "--set", "critic.vlm.max_retries=0", *CHEAP],
        env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while vlm.requests == 0 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert vlm.requests == 1, proc.stderr.read() if proc.poll() is not None else "no request"
        pidfiles = list((store / "prefect" / "embody-servers").glob("*.json"))
        server = json.loads(pidfiles[0].read_text())["server"]
        os.kill(proc.pid, signal.SIGTERM)
        try:
            code = proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            code = None
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        vlm.close()
    assert code is not None, "one SIGTERM did not end a run waiting on the VLM"
    assert code in (130, 143), (code, proc.stderr.read()[-2000:])
    deadline = time.monotonic() + 10
    while _alive(server) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = _alive(server)
    if alive:
        os.kill(server, signal.SIGKILL)
    assert not alive, "the Prefect server outlived the run"
    assert not any(p.exists() for p in pidfiles)


# -- a full disk under the default layout (Prefect's SQLite in <store>/prefect) -----------------------
@pytest.fixture
def small_disk(tmp_path):
    """A 48 MB tmpfs (needs root and mount rights; skipped where mounting is refused)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=48m", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


@pytest.mark.parametrize("free_kb", [512, 2048])
def test_a_full_disk_under_prefects_database_ends_in_a_summary(small_disk, tmp_path, free_kb):
    """The store (and Prefect's database in it) on a disk with `free_kb` left: 512 KB fails
    before the flow (one line), 2 MB during it (Prefect's server answers 500s, its SQLite full);
    either way exit 1 with what is known, no traceback (there were 28)."""
    from toy_flow import write_amass

    data = write_amass(tmp_path / "data", 2, frames=4)
    st = os.statvfs(small_disk)
    filler = small_disk / "filler"
    with open(filler, "wb") as f:
        os.posix_fallocate(f.fileno(), 0, st.f_bavail * st.f_frsize - free_kb * 1024)
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_HOME")}
    env["PYTHONPATH"] = os.pathsep.join(sys.path)
    out = subprocess.run(
        [sys.executable, "-c", "import sys; from embody.cli import main; sys.exit(main())",
         "run", str(data), "--store", str(small_disk / "store"), "--no-progress",
         "--set", "run.report=false", *CHEAP],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert out.returncode == 1, out.stderr[-3000:]
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    assert len(out.stderr.splitlines()) <= 20, out.stderr[-3000:]
    assert "no space left on device" in (out.stdout + out.stderr).lower()
    if "sequences ok" in out.stdout:  # the flow ran: its summary and failures are complete
        assert "verdicts:" in out.stderr
        assert "failed:" in out.stderr or "error:" in out.stderr
    else:
        assert out.stderr.strip().splitlines()[-1].startswith("error: ")


_STUCK = """
import os, sys, time
from embody.flows.env import on_sigterm, register_server
on_sigterm(grace_s=float(sys.argv[1]))
register_server(pid=os.getpid(), home=sys.argv[2])  # a pidfile, as a run with a server has
ready = False
while True:
    try:
        if not ready:
            ready = True
            print("ready", flush=True)
        time.sleep(3600)
    except KeyboardInterrupt:  # work that swallows the interrupt (or cannot see it)
        print("interrupted", flush=True)
"""


@pytest.mark.parametrize("grace_s", [600.0, 0.5])
def test_a_second_sigterm_or_the_grace_period_ends_a_stuck_process(tmp_path, grace_s):
    """A process that does not unwind on SIGTERM exits 143 on the second SIGTERM (grace 600 s)
    or once the grace period passes (0.5 s), its pidfile removed."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-c", _STUCK, str(grace_s), str(tmp_path)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        pidfile = tmp_path / "embody-servers" / f"{proc.pid}.json"
        assert pidfile.is_file()
        os.kill(proc.pid, signal.SIGTERM)
        assert proc.stdout.readline().strip() == "interrupted", proc.stderr.read()[-2000:]
        if grace_s > 60:
            assert proc.poll() is None  # the first SIGTERM left it to unwind
            os.kill(proc.pid, signal.SIGTERM)
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert code == 143 and "stopped (SIGTERM)" in proc.stderr.read()
    assert not pidfile.exists()
