"""A real S3-compatible server on localhost for the object-store tests: moto in server mode.

The store reaches it over HTTP through the same client a user's bucket takes (obstore, with
the standard `AWS_*` variables and `AWS_ENDPOINT_URL`); nothing in-process is mocked. When the
server cannot start, tests skip on a developer machine and fail under `CI=true`.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
import urllib.request
import uuid
from collections.abc import Iterator
from urllib.parse import urlparse

import pytest

from conftest import in_ci

BUCKET = "embody-test"
MOTO_INSTALL = 'pip install "moto[server]>=5.2,<5.3"'


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _unavailable(message: str) -> None:
    if in_ci():
        pytest.fail(f"{message}; CI=true, so this promised check fails instead of skipping",
                    pytrace=False)
    pytest.skip(message)


@pytest.fixture(scope="session")
def s3_endpoint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """`http://127.0.0.1:PORT` of a moto S3 server with bucket `BUCKET`; the `AWS_*` variables
    point at it for this session (and the subprocesses it starts)."""
    try:
        import moto.server  # noqa: F401
        import obstore  # noqa: F401
    except ImportError as exc:
        _unavailable(f"{exc.name} is not installed ({MOTO_INSTALL} obstore)")
    port = _free_port()
    log = tmp_path_factory.mktemp("moto") / "server.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1",
                                 "-p", str(port)], stdout=out, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while True:
        try:
            urllib.request.urlopen(urllib.request.Request(f"{url}/{BUCKET}", method="PUT"),
                                   timeout=5)
            break
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                _unavailable(f"moto's S3 server did not start: {log.read_text()[-500:]}")
            time.sleep(0.2)
    env = {"AWS_ENDPOINT_URL": url, "AWS_ACCESS_KEY_ID": "testing",
           "AWS_SECRET_ACCESS_KEY": "testing", "AWS_REGION": "us-east-1"}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield url
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture
def s3_url(s3_endpoint: str) -> str:
    """A fresh, empty store URL (its own prefix in the test bucket)."""
    return f"s3://{BUCKET}/t-{uuid.uuid4().hex[:12]}"


@pytest.fixture(params=["local", "s3"])
def store_root(request: pytest.FixtureRequest, tmp_path) -> str:
    """A fresh store, once on the local filesystem and once on the S3 server: the tests that
    take it hold the local store's promises on both."""
    if getattr(request, "param", "local") == "local":
        return str(tmp_path / "store")
    return request.getfixturevalue("s3_url")


class StallingProxy:
    """A TCP relay in front of the S3 server that forwards a client's first `stall_after`
    bytes, then stops (`stalled` is set): a writer caught half way through its upload, to be
    killed there. Closing the relay cuts the server's side of the connection too."""

    def __init__(self, endpoint: str, stall_after: int) -> None:
        target = urlparse(endpoint)
        self._target = (target.hostname, target.port)
        self._left = stall_after
        self.stalled = threading.Event()
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self._listener.getsockname()[1]}"
        self._sockets: list[socket.socket] = [self._listener]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            upstream = socket.create_connection(self._target)
            self._sockets += [client, upstream]
            threading.Thread(target=self._pump, args=(client, upstream, True), daemon=True).start()
            threading.Thread(target=self._pump, args=(upstream, client, False), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, counted: bool) -> None:
        try:
            while data := src.recv(65536):
                if counted:
                    data = data[:max(self._left, 0)]
                    self._left -= len(data)
                    if self._left <= 0:
                        dst.sendall(data)
                        self.stalled.set()
                        return
                dst.sendall(data)
        except OSError:
            pass

    def __enter__(self) -> "StallingProxy":
        return self

    def __exit__(self, *exc: object) -> None:
        for s in self._sockets:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()
