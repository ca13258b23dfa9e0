"""The VLM client against a real local HTTP server speaking Chat Completions.

Cases: valid reply, malformed JSON, unknown primitive, 429 then success, timeout, missing key,
request budget; and a sentinel API key that must never leak into records, logs or exceptions.
"""

import base64
import hashlib
import json
import logging
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from embody.config.critic import VLMConfig
from embody.critic.action import Limits
from embody.critic.base import CritiqueContext
from embody.critic.vlm import VLMClient, VLMCritic, VLMError
from embody.errors import ConfigError

SENTINEL = "sk-SENTINEL-7f3a9c1e-do-not-leak"
T = 10


class FakeServer:
    """Answers POST /v1/chat/completions from a script of (status, body, headers, delay)."""

    def __init__(self):
        self.script: list[tuple[int, str, dict, float]] = []
        self.requests: list[dict] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self):  # noqa: N802 - http.server API
                length = int(self.headers.get("Content-Length", 0))
                body = json.loads(self.rfile.read(length))
                server.requests.append({"path": self.path, "headers": dict(self.headers), "body": body})
                status, text, headers, delay = (server.script.pop(0) if server.script
                                                else (500, "script exhausted", {}, 0.0))
                time.sleep(delay)
                if callable(text):  # the answer writes itself (trickles, floods)
                    try:
                        text(self)
                    except (BrokenPipeError, ConnectionResetError):
                        pass
                    return
                try:
                    self.send_response(status)
                    for k, v in headers.items():
                        self.send_header(k, v)
                    self.send_header("Content-Type", "application/json")
                    self.end_headers()
                    self.wfile.write(text.encode())
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the client timed out and left

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"

    def reply(self, content: str, status: int = 200, headers: dict | None = None, delay: float = 0.0):
        body = {"id": "x", "object": "chat.completion", "model": "fake",
                "choices": [{"index": 0, "message": {"role": "assistant", "content": content},
                             "finish_reason": "stop"}]}
        self.script.append((status, json.dumps(body), headers or {}, delay))

    def error(self, status: int, headers: dict | None = None, delay: float = 0.0):
        self.script.append((status, json.dumps({"error": {"message": "busy"}}), headers or {}, delay))

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def server():
    s = FakeServer()
    yield s
    s.close()


@pytest.fixture
def key(monkeypatch):
    monkeypatch.setenv("EMBODY_VLM_API_KEY", SENTINEL)
    return SENTINEL


def _cfg(server, **kw):
    base = dict(base_url=server.url, model="fake-vl", timeout_s=2.0, max_retries=2, backoff_s=0.01)
    return VLMConfig(**{**base, **kw})


def _png(value: int) -> bytes:
    from embody.render.sheet import png_bytes

    return png_bytes(np.full((8, 8, 3), value, dtype=np.uint8))


def _context():
    pos = np.zeros((T, 2, 3))
    rot = np.tile(np.eye(3), (T, 2, 1, 1))
    return CritiqueContext(0, 30.0, 0.45, pos, rot, pos, rot, Limits(T), sheet_png=_png(10),
                           keyframe_pngs=[_png(20), _png(30)], keyframes=[2, 7], text="hello")


VALID = json.dumps({"primitives_positions": [{"name": "move_left_up", "amount": 0.05, "window": [1, 4]}],
                    "primitives_orientation": ["right_yaw_in"], "verdict": "revise",
                    "reason": "left hand too low"})


def _no_sentinel(*texts):
    for text in texts:
        assert SENTINEL not in text


def test_valid_reply_request_shape_and_record(server, key, caplog):
    caplog.set_level(logging.DEBUG)
    server.reply(VALID)
    critic = VLMCritic(_cfg(server))
    ctx = _context()
    action = critic.critique(ctx)
    assert action.valid and action.verdict == "revise"
    assert [(p.name, p.amount, p.window) for p in action.primitives] == [
        ("move_left_up", 0.05, (1, 4)), ("right_yaw_in", 20.0, None)]
    (req,) = server.requests
    assert req["path"] == "/v1/chat/completions"
    assert req["headers"]["Authorization"] == f"Bearer {SENTINEL}"
    body = req["body"]
    assert body["model"] == "fake-vl"
    rf = body["response_format"]
    assert rf["type"] == "json_schema" and rf["json_schema"]["strict"] is True
    assert set(rf["json_schema"]["schema"]["required"]) == {
        "primitives_positions", "primitives_orientation", "verdict", "reason"}
    assert "critic" in body["messages"][0]["content"]  # the prompt from configs/critic/prompt.md
    images = [p["image_url"]["url"] for p in body["messages"][1]["content"] if p["type"] == "image_url"]
    assert len(images) == 3 and all(u.startswith("data:image/png;base64,") for u in images)
    assert base64.b64decode(images[0].split(",", 1)[1]) == ctx.sheet_png
    # the record references images by hash, never inline
    record = json.dumps(ctx.record)
    assert "base64" not in record
    assert hashlib.sha256(ctx.sheet_png).hexdigest() in record
    assert ctx.record["response"]["choices"][0]["message"]["content"] == VALID
    _no_sentinel(record, *(r.getMessage() for r in caplog.records))


@pytest.mark.parametrize("content, why", [
    ("this is not json {", "malformed JSON"),
    (json.dumps({"primitives_positions": ["move_left_teleport"], "primitives_orientation": [],
                 "verdict": "revise", "reason": "x"}), "schema violation"),
])
def test_malformed_or_unknown_replies_are_no_action(server, key, content, why):
    server.reply(content)
    action = VLMCritic(_cfg(server)).critique(_context())
    assert not action.valid and action.primitives == () and why in action.error


def test_429_then_success_honours_retry_after(server, key):
    server.error(429, headers={"Retry-After": "0.3"})
    server.error(503)
    server.reply(VALID)
    delays: list[float] = []
    client = VLMClient(_cfg(server, backoff_s=0.01, max_backoff_s=5.0), sleep=delays.append)
    action = VLMCritic(_cfg(server), client=client).critique(ctx := _context())
    assert action.valid
    assert len(server.requests) == 3 and client.requests_sent == 3
    assert delays == [pytest.approx(0.3), pytest.approx(0.02)]  # Retry-After, then 2× backoff
    assert [a["status"] for a in ctx.record["attempts"]] == [429, 503, 200]


def test_timeout_fails_the_sequence_with_a_clear_error(server, key, caplog):
    caplog.set_level(logging.DEBUG)
    server.reply(VALID, delay=1.0)
    server.reply(VALID, delay=1.0)
    client = VLMClient(_cfg(server, timeout_s=0.2, max_retries=1), sleep=lambda s: None)
    with pytest.raises(VLMError, match="unavailable after 2 attempts") as exc:
        VLMCritic(_cfg(server), client=client).critique(_context())
    _no_sentinel(str(exc.value), repr(exc.value), *(r.getMessage() for r in caplog.records))


def test_unreachable_endpoint_and_missing_key(monkeypatch, key):
    cfg = VLMConfig(base_url="http://127.0.0.1:9/v1", timeout_s=0.5, max_retries=0)
    with pytest.raises(VLMError, match="unavailable") as exc:
        VLMCritic(cfg).critique(_context())
    _no_sentinel(str(exc.value))
    monkeypatch.delenv("EMBODY_VLM_API_KEY")
    with pytest.raises(ConfigError, match="EMBODY_VLM_API_KEY"):
        VLMClient(cfg)
    VLMClient(cfg.model_copy(update={"api_key_required": False}))  # local servers need none


def test_request_budget_and_non_retryable_errors(server, key):
    server.reply(VALID)
    server.reply(VALID)
    client = VLMClient(_cfg(server, request_budget=1))
    critic = VLMCritic(_cfg(server), client=client)
    assert critic.critique(_context()).valid
    with pytest.raises(VLMError, match="budget of 1 exhausted"):
        critic.critique(_context())
    server.script.clear()
    server.error(401)
    with pytest.raises(VLMError, match="HTTP 401") as exc:
        VLMCritic(_cfg(server)).critique(_context())
    _no_sentinel(str(exc.value))


def test_key_echoed_by_a_server_is_scrubbed(server, key):
    server.reply(json.dumps({"primitives_positions": [], "primitives_orientation": [],
                             "verdict": "accept", "reason": f"your key is {SENTINEL}"}))
    ctx = _context()
    action = VLMCritic(_cfg(server)).critique(ctx)
    assert action.accepted and "***" in action.reason
    _no_sentinel(json.dumps(ctx.record), json.dumps(action.to_json()), action.raw)


def test_fidelity_numbers_reach_the_prompt(server, key):
    """The measured location error per hand, its nearest landmark and the palm angle are sent."""
    server.reply(VALID)
    ctx = _context()
    ctx.hand_fidelity = {
        "left": {"landmark": "belly", "share": 0.5, "location_err": 0.1, "location_cm": 3.0, "palm_deg": 12.0},
        "right": {"landmark": "chin", "share": 0.75, "location_err": 0.25, "location_cm": 7.4, "palm_deg": 31.5}}
    VLMCritic(_cfg(server)).critique(ctx)
    (req,) = server.requests
    text = " ".join(p["text"] for p in req["body"]["messages"][1]["content"] if p["type"] == "text")
    assert ("Measured right hand: nearest body landmark chin (75% of frames); palm location error 7.4 cm "
            "(0.25 body scales)") in text
    assert "palm orientation error 31.5 deg" in text and "nearest body landmark belly (50%" in text
    # without measurements nothing is claimed
    server.requests.clear()
    server.reply(VALID)
    VLMCritic(_cfg(server)).critique(_context())
    user = server.requests[0]["body"]["messages"][1]["content"]
    assert "Measured" not in " ".join(p["text"] for p in user if p["type"] == "text")


# -- hostile servers: trickled and oversized answers --------------------------------------------------
def _trickle_headers(handler):
    """The status line one byte at a time, forever: every read returns within the timeout."""
    while True:
        for byte in b"HTTP/1.1 200 OK\r\nX-Slow: ":
            handler.wfile.write(bytes([byte]))
            handler.wfile.flush()
            time.sleep(0.1)
        while True:
            handler.wfile.write(b"a")
            handler.wfile.flush()
            time.sleep(0.1)


def _trickle_body(handler):
    """Headers at once, then a byte of an endless body every 0.1 s."""
    handler.send_response(200)
    handler.send_header("Content-Type", "application/json")
    handler.send_header("Content-Length", "1000000")
    handler.end_headers()
    while True:
        handler.wfile.write(b" ")
        handler.wfile.flush()
        time.sleep(0.1)


def _in_thread(fn):
    """Run `fn` in a daemon thread; what it returned or raised, or None if still running at 60 s
    (a request the deadline does not end would run forever against these servers)."""
    out: dict = {}

    def target():
        try:
            out["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            out["error"] = exc
    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(60)
    return None if t.is_alive() else out


@pytest.mark.parametrize("answer", [_trickle_headers, _trickle_body])
def test_timeout_is_a_deadline_over_the_whole_request(server, key, answer):
    server.script.append((200, answer, {}, 0.0))
    client = VLMClient(_cfg(server, timeout_s=1.0, max_retries=0))
    out = _in_thread(lambda: client.chat({"model": "m", "messages": []}))
    assert out is not None, "a trickling server held the request past its deadline"
    assert isinstance(out.get("error"), VLMError), out
    assert "no complete answer within 1 s" in str(out["error"])


def _flood(handler, total=64 * 2**20, declare=False):
    """A 64 MB answer, with or without a Content-Length; counts what it managed to send."""
    handler.send_response(200)
    handler.send_header("Content-Type", "application/json")
    if declare:
        handler.send_header("Content-Length", str(total))
    handler.end_headers()
    chunk = b"[" * 65536
    handler.server.sent = 0
    while handler.server.sent < total:
        handler.wfile.write(chunk)
        handler.server.sent += len(chunk)


@pytest.mark.parametrize("declare", [False, True])
def test_an_oversized_answer_is_refused_without_reading_it_whole(server, key, declare):
    server.script.append((200, lambda h: _flood(h, declare=declare), {}, 0.0))
    client = VLMClient(_cfg(server, max_retries=0), max_response_bytes=100_000)
    with pytest.raises(VLMError, match="100,000"):
        client.chat({"model": "m", "messages": []})
    deadline = time.monotonic() + 30
    while getattr(server.httpd, "sent", None) is None and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.5)  # the server writes until it notices the client left
    assert server.httpd.sent < 32 * 2**20  # the client stopped reading long before the end


def test_a_normal_answer_still_fits_and_parses(server, key):
    server.reply(VALID)
    client = VLMClient(_cfg(server), max_response_bytes=2048)
    reply, attempts = client.chat({"model": "m", "messages": []})
    assert json.loads(reply["choices"][0]["message"]["content"])["verdict"] == "revise"
    assert attempts == [{"status": 200}]
