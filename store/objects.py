"""Object storage under the artifact store (S3, GCS, Azure), through obstore.

An object store has no rename and no `flock`; what it has are conditional writes, and the
store's promises rest on those: `put(..., create=True)` (S3 `If-None-Match: *`) succeeds for
exactly one writer of a key, and `put(..., etag=E)` (S3 `If-Match: E`) only while the object is
still the version that writer read, a compare-and-swap. obstore exposes both for S3, GCS and
Azure alike (`PutMode.Create` / `PutMode.Update`), so one client serves every provider. fsspec's s3fs exposes only
the create half, and its aiobotocore pins a botocore older than the one moto's server needs.

URLs are `s3://bucket/prefix`, `gs://bucket/prefix` and `az://container/prefix`; credentials
and endpoint come from the provider's standard environment variables (for S3:
`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_REGION`, `AWS_ENDPOINT_URL`). An `http://`
endpoint (a server on localhost) is allowed.

obstore runs its requests on a tokio runtime, which does not survive `fork`: a process forked
after its parent used the store would hang on its first request, so it gets an error instead.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable, Iterator
from typing import Any

__all__ = ["Conflict", "Objects", "SCHEMES", "is_url"]

#: URL schemes served by `Objects` (`file://` is the local store: POSIX gives it more).
SCHEMES = ("s3", "gs", "az", "abfs", "abfss", "azure")
#: Requests one call keeps in flight (a 20k-sequence run's counters are read in one call).
_IN_FLIGHT = 32
_PARENT_USED = False
_USED = False


def _after_fork() -> None:
    global _PARENT_USED
    _PARENT_USED = _PARENT_USED or _USED


os.register_at_fork(after_in_child=_after_fork)


def is_url(text: str) -> bool:
    """`scheme://...` for an object store (not `file://`, which names a local folder)."""
    scheme, sep, _ = str(text).partition("://")
    return bool(sep) and scheme.lower() in SCHEMES


class Conflict(Exception):
    """A conditional write lost: the key exists (create) or changed since it was read (etag)."""


def _client_options() -> dict[str, Any]:
    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL") or ""
    return {"allow_http": True} if endpoint.startswith("http://") else {}


class Objects:
    """Keys under one URL prefix: get/put (conditional)/delete/list."""

    def __init__(self, url: str) -> None:
        self.url = url.rstrip("/")
        self._store: Any = None
        self._pid = -1

    @property
    def store(self) -> Any:
        """The obstore store, built in this process (never one inherited across a fork)."""
        global _USED
        if _PARENT_USED:
            raise RuntimeError("the object store cannot be used in a process forked after its "
                               "parent used it (obstore's runtime does not survive fork): "
                               "start worker processes before the first store access, or spawn them")
        if self._store is None or self._pid != os.getpid():
            from obstore.store import from_url

            kwargs: dict[str, Any] = {}
            if self.url.startswith("s3://"):
                kwargs["client_options"] = _client_options()
            self._store = from_url(self.url, **kwargs)
            self._pid = os.getpid()
        _USED = True
        return self._store

    def get(self, key: str) -> tuple[bytes, str | None] | None:
        """(bytes, ETag), or None when the key does not exist."""
        import obstore

        try:
            result = obstore.get(self.store, key)
        except FileNotFoundError:
            return None
        return bytes(result.bytes()), result.meta.get("e_tag")

    def get_head(self, key: str, length: int) -> tuple[bytes, int] | None:
        """The first `length` bytes (all of a shorter object) and the object's size, in one
        request; None when the key does not exist."""
        import obstore

        try:
            result = obstore.get(self.store, key, options={"range": (0, length)})
        except FileNotFoundError:
            return None
        return bytes(result.bytes()), int(result.meta["size"])

    def head(self, key: str) -> dict[str, Any] | None:
        import obstore

        try:
            return dict(obstore.head(self.store, key))
        except FileNotFoundError:
            return None

    def put(self, key: str, data: bytes, *, create: bool = False,
            etag: str | None = None) -> str | None:
        """Write `data` in one request (an object appears whole or not at all: never a multipart
        upload); with `create` only if the key is absent, with `etag` only if the key is still
        that version; Conflict otherwise. Returns the new ETag."""
        import obstore
        from obstore.exceptions import AlreadyExistsError, PreconditionError

        mode: Any = "overwrite"
        if create:
            mode = "create"
        elif etag is not None:
            mode = {"e_tag": etag}
        try:
            return obstore.put(self.store, key, data, mode=mode,
                               use_multipart=False).get("e_tag")
        except (AlreadyExistsError, PreconditionError) as exc:
            raise Conflict(key) from exc

    def put_many(self, items: dict[str, bytes]) -> None:
        """Unconditional writes of several keys, sent concurrently."""
        import asyncio

        import obstore

        store = self.store
        if _loop_running():
            for k, v in items.items():
                obstore.put(store, k, v, use_multipart=False)
            return

        async def send() -> None:
            gate = asyncio.Semaphore(_IN_FLIGHT)

            async def one(k: str, v: bytes) -> None:
                async with gate:
                    await obstore.put_async(store, k, v, use_multipart=False)
            await asyncio.gather(*(one(k, v) for k, v in items.items()))
        asyncio.run(send())

    def get_many(self, keys: Iterable[str]) -> dict[str, bytes]:
        """Several keys fetched concurrently; absent ones are left out."""
        import asyncio

        import obstore

        store, keys = self.store, list(keys)
        if _loop_running():
            got = {k: self.get(k) for k in keys}
            return {k: v[0] for k, v in got.items() if v is not None}

        async def fetch() -> list[bytes | None]:
            gate = asyncio.Semaphore(_IN_FLIGHT)

            async def one(k: str) -> bytes | None:
                async with gate:
                    try:
                        return bytes(await (await obstore.get_async(store, k)).bytes_async())
                    except FileNotFoundError:
                        return None
            return await asyncio.gather(*(one(k) for k in keys))
        return {k: v for k, v in zip(keys, asyncio.run(fetch())) if v is not None}

    def delete(self, keys: Iterable[str]) -> None:
        import obstore

        keys = list(keys)
        for i in range(0, len(keys), 1000):
            try:
                obstore.delete(self.store, keys[i:i + 1000])
            except FileNotFoundError:
                pass

    def list(self, prefix: str) -> Iterator[dict[str, Any]]:
        """Every object under `prefix/` (path relative to the store URL, size, last_modified)."""
        import obstore

        for batch in obstore.list(self.store, prefix=_folder(prefix)):
            yield from batch

    def children(self, prefix: str) -> list[str]:
        """The names one level below `prefix/` (folders and objects)."""
        import obstore

        out = obstore.list_with_delimiter(self.store, prefix=_folder(prefix))
        names = [p.rstrip("/").rsplit("/", 1)[-1] for p in out["common_prefixes"]]
        return sorted(names + [o["path"].rsplit("/", 1)[-1] for o in out["objects"]])


def _folder(prefix: str) -> str | None:
    """`a/b` → `a/b/` (objects below it, not `a/bc`); `` → the whole store."""
    prefix = prefix.strip("/")
    return prefix + "/" if prefix else None


def _loop_running() -> bool:
    """An event loop runs in this thread (`asyncio.run` would refuse): send one at a time."""
    import asyncio

    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


def mtime(meta: dict[str, Any]) -> float:
    """An object's last-modified time in epoch seconds."""
    stamp = meta.get("last_modified")
    return stamp.timestamp() if stamp is not None else time.time()
