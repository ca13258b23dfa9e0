"""A VLM critic over any OpenAI-compatible Chat Completions server, with only the stdlib.

Works with vLLM (`/v1`), Ollama (`http://localhost:11434/v1`) and llama.cpp's `llama-server`:
the reply is constrained with `response_format={"type": "json_schema", ...}`, the schema at
`json_schema.schema` (the only place llama.cpp reads it). Transient failures (429, 5xx,
timeouts, refused connections) are retried with exponential backoff, honouring `Retry-After`;
a per-client request budget caps a run. Every exchange is recorded with images replaced by their
sha256, and the API key is scrubbed from anything recorded or raised: it lives only in the
Authorization header.

Key hygiene: the key is stripped and validated when the client is built (a key read from a
secret file often ends in a newline, and `http.client` would echo `Bearer <key>` in its
error); every exception leaving `chat` is re-raised as a scrubbed `VLMError`; redirects are
refused, so the Authorization header never travels to another host or scheme.

Bounds: `timeout_s` is a deadline over the whole request (a watchdog shuts the request's socket
down when it passes, so a server trickling a byte at a time cannot hold a run), the answer is
read in chunks and refused past `MAX_RESPONSE_BYTES` (a fixed bound rather than a config key,
which would enter the refine step's content key), and `abort_requests` (called on SIGTERM)
ends every request in flight at once.
"""

from __future__ import annotations

import base64
import hashlib
import http.client
import json
import logging
import os
import socket
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any, Callable

import numpy as np

from embody.config.critic import VLMConfig
from embody.critic.action import ACTION_SCHEMA, Action
from embody.critic.base import Critic, CritiqueContext
from embody.errors import ConfigError, EmbodyError

log = logging.getLogger(__name__)

_RETRY_STATUS = {408, 409, 425, 429, 500, 502, 503, 504}


class VLMError(EmbodyError):
    """The VLM could not be asked (no key, unreachable, budget spent, HTTP error): fails the sequence."""


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def default_prompt_path() -> Path:
    from embody.config import configs_dir

    return configs_dir() / "critic" / "prompt.md"


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    """Refuse every redirect: urllib would forward `Authorization` to the new location."""

    def redirect_request(self, req, fp, code, msg, headers, newurl):  # noqa: ANN001
        return None  # urllib then raises the 3xx as an HTTPError


_CHUNK = 64 * 1024
#: Largest answer read (bytes): a reply of `max_tokens` ≤ 32,768 tokens is well under 1 MB.
MAX_RESPONSE_BYTES = 4_000_000


class _Deadline:
    """One request's deadline: at `seconds` from now (monotonic) the sockets it opened are shut
    down, which ends any read blocked on them; `abort` does the same at once."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.expired = self.aborted = False
        self._socks: list[socket.socket] = []
        self._lock = threading.Lock()
        self._timer = threading.Timer(seconds, self._expire)
        self._timer.daemon = True

    def __enter__(self) -> "_Deadline":
        with _ACTIVE_LOCK:
            if _ABORTED.is_set():
                raise VLMError("VLM request not sent: the run is being stopped")
            _ACTIVE.add(self)
        self._timer.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._timer.cancel()
        with _ACTIVE_LOCK:
            _ACTIVE.discard(self)

    def _shut(self) -> None:
        for sock in self._socks:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def _expire(self) -> None:
        with self._lock:
            self.expired = True
            self._shut()

    def abort(self) -> None:
        with self._lock:
            self.aborted = self.expired = True
            self._shut()

    def track(self, sock: socket.socket) -> socket.socket:
        with self._lock:
            self._socks.append(sock)
            if self.expired:
                self._shut()
        return sock

    def connection(self, http_class: Any) -> Callable[..., http.client.HTTPConnection]:
        """`http_class` whose sockets this deadline tracks (for urllib's `do_open`)."""
        def make(*args: Any, **kwargs: Any) -> http.client.HTTPConnection:
            conn = http_class(*args, **kwargs)
            create = conn._create_connection
            conn._create_connection = lambda *a, **k: self.track(create(*a, **k))
            return conn
        return make


_ACTIVE: set[_Deadline] = set()
_ACTIVE_LOCK = threading.Lock()
_ABORTED = threading.Event()


def abort_requests() -> None:
    """End every VLM request in flight now and refuse new ones (the process is stopping)."""
    with _ACTIVE_LOCK:
        _ABORTED.set()
        active = list(_ACTIVE)
    for deadline in active:
        deadline.abort()


def _opener(deadline: _Deadline) -> urllib.request.OpenerDirector:
    """urllib without redirects, whose HTTP(S) connections `deadline` can shut down."""
    class HTTP(urllib.request.HTTPHandler):
        def do_open(self, http_class, req, **kw):  # noqa: ANN001
            return super().do_open(deadline.connection(http_class), req, **kw)

    class HTTPS(urllib.request.HTTPSHandler):
        def do_open(self, http_class, req, **kw):  # noqa: ANN001
            return super().do_open(deadline.connection(http_class), req, **kw)

    return urllib.request.build_opener(_NoRedirect, HTTP, HTTPS)


def _read_capped(resp: Any, limit: int, url: str) -> bytes:
    """The response body, read in chunks; VLMError as soon as it passes `limit` bytes."""
    length = resp.headers.get("Content-Length")
    if length is not None and length.strip().isdigit() and int(length) > limit:
        raise VLMError(f"VLM endpoint {url} answered {int(length):,} bytes, more than "
                       f"the {limit:,} accepted")
    body = bytearray()
    while chunk := resp.read(_CHUNK):
        body += chunk
        if len(body) > limit:
            raise VLMError(f"VLM endpoint {url} answered more than the {limit:,} bytes "
                           "accepted")
    return bytes(body)


def api_key(cfg: VLMConfig) -> str | None:
    """The API key from `cfg.api_key_env`, stripped; ConfigError (naming the variable, never the
    value) when it is missing but required, or not a printable single-line token."""
    raw = os.environ.get(cfg.api_key_env)
    key = raw.strip() if raw is not None else None
    if not key:
        if cfg.api_key_required:
            raise ConfigError("critic.vlm.api_key_env",
                              f"VLM API key missing: set the environment variable {cfg.api_key_env} "
                              "(or critic.vlm.api_key_required=false for a local server)")
        return None
    if any(not (0x21 <= ord(c) <= 0x7E) for c in key):
        raise ConfigError("critic.vlm.api_key_env",
                          f"the key in {cfg.api_key_env} contains spaces, control or non-ASCII "
                          "characters (check the secret file)")
    return key


def check_base_url(cfg: VLMConfig) -> str:
    """`base_url` must be http(s) with a host; ConfigError otherwise (file://, ftp://, ...)."""
    from urllib.parse import urlsplit

    parts = urlsplit(cfg.base_url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ConfigError("critic.vlm.base_url",
                          f"must be an http(s) URL with a host, got {cfg.base_url!r}")
    return cfg.base_url


def check_config(cfg: VLMConfig) -> None:
    """What `VLMClient` would refuse, checked before a run starts (exit 2, nothing written)."""
    check_base_url(cfg)
    api_key(cfg)


class VLMClient:
    """Chat Completions over `urllib`; one instance per run so the request budget is per run."""

    def __init__(self, cfg: VLMConfig, *, sleep: Callable[[float], None] = time.sleep,
                 max_response_bytes: int = MAX_RESPONSE_BYTES) -> None:
        self.cfg = cfg
        self.max_response_bytes = max_response_bytes
        self.requests_sent = 0
        self._sleep = sleep
        check_base_url(cfg)
        self._raw = os.environ.get(cfg.api_key_env) or None
        self._key = api_key(cfg)

    def scrub(self, text: str) -> str:
        """The text with the API key (if any, raw or stripped) replaced: for everything
        recorded or raised."""
        for secret in (self._raw, self._key, self._raw.strip() if self._raw else None):
            if secret:
                text = text.replace(secret, "***")
        return text

    def chat(self, payload: dict[str, Any]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        """POST /chat/completions; returns the reply JSON and one record per attempt.

        Whatever goes wrong, what leaves is a `VLMError` whose text has the key scrubbed.
        """
        try:
            return self._chat(payload)
        except VLMError as exc:
            raise VLMError(self.scrub(str(exc))) from None
        except Exception as exc:
            raise VLMError(self.scrub(f"VLM request failed: {type(exc).__name__}: {exc}")) from None

    def _chat(self, payload: dict[str, Any]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        url = self.cfg.base_url.rstrip("/") + "/chat/completions"
        body = json.dumps(payload).encode()
        headers = {"Content-Type": "application/json", "Accept": "application/json"}
        if self._key:
            headers["Authorization"] = f"Bearer {self._key}"
        attempts: list[dict[str, Any]] = []
        for attempt in range(self.cfg.max_retries + 1):
            if self.requests_sent >= self.cfg.request_budget:
                raise VLMError(f"VLM request budget of {self.cfg.request_budget} exhausted")
            self.requests_sent += 1
            retry_after: float | None = None
            deadline = _Deadline(self.cfg.timeout_s)
            try:
                with deadline:
                    req = urllib.request.Request(url, data=body, headers=headers, method="POST")
                    with _opener(deadline).open(req, timeout=self.cfg.timeout_s) as resp:
                        raw = _read_capped(resp, self.max_response_bytes, url)
                        status = resp.status
                if deadline.expired:  # the body ended because the watchdog closed the socket
                    raise TimeoutError(f"no complete answer within {self.cfg.timeout_s:g} s")
                text = raw.decode("utf-8", errors="replace")
                attempts.append({"status": status})
                try:
                    return json.loads(text), attempts
                except json.JSONDecodeError:
                    raise VLMError(f"VLM endpoint {url} answered non-JSON: "
                                   f"{self.scrub(text[:200])!r}") from None
            except urllib.error.HTTPError as exc:
                try:
                    detail = self.scrub(exc.read(4096).decode("utf-8", errors="replace")[:300])
                except (OSError, http.client.HTTPException):
                    detail = ""
                attempts.append({"status": exc.code, "error": detail})
                if 300 <= exc.code < 400:
                    raise VLMError(f"VLM endpoint {url} answered a redirect (HTTP {exc.code}); "
                                   "redirects are refused so the API key stays with "
                                   "critic.vlm.base_url: set base_url to the final URL") from None
                if exc.code not in _RETRY_STATUS:
                    raise VLMError(f"VLM endpoint {url} answered HTTP {exc.code}: {detail}") from None
                retry_after = _retry_after(exc.headers.get("Retry-After"))
                failure = f"HTTP {exc.code}"
            except (urllib.error.URLError, OSError, http.client.HTTPException) as exc:
                if deadline.aborted:
                    raise VLMError("VLM request aborted: the run is being stopped") from None
                reason = getattr(exc, "reason", exc)
                if deadline.expired:
                    reason = TimeoutError(f"no complete answer within {self.cfg.timeout_s:g} s")
                failure = self.scrub(f"{type(reason).__name__}: {reason}")
                attempts.append({"status": None, "error": failure})
            if attempt == self.cfg.max_retries:
                raise VLMError(f"VLM endpoint {url} unavailable after {attempt + 1} attempts: {failure}")
            delay = min(self.cfg.backoff_s * 2 ** attempt, self.cfg.max_backoff_s)
            if retry_after is not None:
                delay = min(max(delay, retry_after), self.cfg.max_backoff_s)
            log.warning("VLM request failed (%s); retrying in %.2fs", failure, delay)
            self._sleep(delay)
            if _ABORTED.is_set():
                raise VLMError("VLM request aborted: the run is being stopped")
        raise AssertionError("unreachable")


def _retry_after(value: str | None) -> float | None:
    """Seconds from a Retry-After header (delta-seconds form; HTTP dates are ignored)."""
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None


def _image_part(png: bytes) -> dict[str, Any]:
    url = "data:image/png;base64," + base64.b64encode(png).decode("ascii")
    return {"type": "image_url", "image_url": {"url": url}}


def redact_images(payload: dict[str, Any]) -> dict[str, Any]:
    """A copy of a request with every inline image replaced by its sha256 and size."""
    out = json.loads(json.dumps(payload))
    for message in out.get("messages", []):
        content = message.get("content")
        if not isinstance(content, list):
            continue
        for part in content:
            url = part.get("image_url", {}).get("url", "")
            if url.startswith("data:"):
                data = base64.b64decode(url.split(",", 1)[1])
                part["image_url"] = {"sha256": sha256(data), "bytes": len(data)}
    return out


def _fidelity_facts(context: CritiqueContext) -> str:
    """The measured sign fidelity of this round, as sentences (empty when not measured)."""
    out = ""
    for side, h in context.hand_fidelity.items():
        out += (f" Measured {side} hand: nearest body landmark {h['landmark']} "
                f"({100 * h['share']:.0f}% of frames); palm location error {h['location_cm']:.1f} cm "
                f"({h['location_err']:.2f} body scales) from where the human's palm sits relative to it; "
                f"palm orientation error {h['palm_deg']:.1f} deg.")
    if context.reach_blocked is not None:  # what the geometric critic does not ask for either
        for s, side in enumerate(("left", "right")):
            n = int(np.count_nonzero(context.reach_blocked[:, s]))
            if n:
                out += (f" In {n} frames the robot's {side} hand already stands at its clearance from "
                        "the face or chest: it cannot move closer to them there.")
    return out


class VLMCritic(Critic):
    """Sends the critique prompt, the comparison sheet and keyframes; parses the JSON action."""

    needs_images = True

    def __init__(self, cfg: VLMConfig, client: VLMClient | None = None) -> None:
        self.cfg = cfg
        self.client = client or VLMClient(cfg)
        path = Path(cfg.prompt_path) if cfg.prompt_path else default_prompt_path()
        try:
            self.prompt = path.read_text()
        except OSError as exc:
            raise ConfigError("critic.vlm.prompt_path", f"cannot read {path}: {exc.strerror}") from None

    def payload(self, context: CritiqueContext) -> dict[str, Any]:
        facts = (f"Sequence: {context.num_frames} frames at {context.fps:g} fps. "
                 f"Keyframes shown (columns, frame indices): {context.keyframes}. "
                 f"Round {context.round}. Default amounts: {context.limits.position_step_m:g} m, "
                 f"{context.limits.angle_step_deg:g} deg; largest: {context.limits.max_position_m:g} m, "
                 f"{context.limits.max_angle_deg:g} deg. Windows are inclusive frame indices "
                 f"0..{context.num_frames - 1}.")
        if context.text:
            facts += f" Sign text: {context.text!r}."
        facts += _fidelity_facts(context)
        content: list[dict[str, Any]] = [{"type": "text", "text": facts}]
        if context.sheet_png is not None:
            content += [{"type": "text", "text": "Comparison sheet (top: human reference, bottom: robot):"},
                        _image_part(context.sheet_png)]
        if self.cfg.send_keyframes:
            for frame, png in zip(context.keyframes, context.keyframe_pngs):
                content += [{"type": "text", "text": f"Frame {frame} (top: human, bottom: robot):"},
                            _image_part(png)]
        return {
            "model": self.cfg.model,
            "messages": [{"role": "system", "content": self.prompt},
                         {"role": "user", "content": content}],
            "temperature": self.cfg.temperature,
            "max_tokens": self.cfg.max_tokens,
            "response_format": {"type": "json_schema", "json_schema": {
                "name": "embody_critic_action", "strict": True, "schema": ACTION_SCHEMA}},
        }

    def critique(self, context: CritiqueContext) -> Action:
        payload = self.payload(context)
        record: dict[str, Any] = {"request": redact_images(payload)}
        context.record.update(record)
        reply, attempts = self.client.chat(payload)
        context.record["attempts"] = attempts
        context.record["response"] = json.loads(self.client.scrub(json.dumps(reply)))
        try:
            content = reply["choices"][0]["message"]["content"]
        except (KeyError, IndexError, TypeError):
            return Action.rejected("reply has no choices[0].message.content")
        if not isinstance(content, str):
            return Action.rejected(f"reply content is {type(content).__name__}, not text")
        return Action.parse(self.client.scrub(content), context.limits)

