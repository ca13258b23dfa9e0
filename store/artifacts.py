"""The artifact store: one zarr v3 group per artifact, published atomically.

Layout under the store root::

    artifacts/<step>/<key[:2]>/<key>/     zarr group: arrays + attrs {"embody": info, "result": attrs}
    counters/<step>.jsonl                 one line per computation (what tests and benchmarks count)
    runs/<run>/manifest.json              see `store.manifest`

A group is written under a temporary sibling name and renamed into place, so a reader either
sees a complete artifact or none, and a killed writer leaves only a temp that `gc` removes.
Directory renames are atomic on one filesystem and fail when the target exists, which is what
makes concurrent writers (threads, processes, Dask workers) safe: the loser discards its temp.

On an object store (`s3://bucket/prefix`, `gs://`, `az://`: `store.objects`) there is no
rename, and every request is a round trip, so the group's files go into one object, a zip
(`store.packed`, what zarr's `ZipStore` reads), published by one create-only PUT (S3
`If-None-Match: *`)::

    artifacts/<step>/<kk>/<key>/zarr.zip      the artifact: exactly one writer creates it
    counters/<step>/<time>-<writer>.json      one object per computation (no append)

An object store applies a PUT whole or not at all, so a reader sees the whole artifact or none,
a killed writer leaves nothing, and a losing writer has nothing to clean up. A cache-hit check
reads the zip's head (the group's `zarr.json`, its first member) in one ranged GET; a read is
one GET.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import time
import uuid
from dataclasses import dataclass
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np
import zarr

from embody.errors import ConfigError, EmbodyError
from embody.store import packed
from embody.store.keys import arrays_checksum
from embody.store.objects import Conflict, Objects, is_url, mtime

__all__ = ["Artifact", "ArtifactStore", "CorruptArtifact", "array_digest", "jsonable",
           "package_versions"]


class CorruptArtifact(EmbodyError):
    """A stored artifact whose bytes no longer match the digests recorded when it was written."""

    def __init__(self, step: str, key: str, problem: str) -> None:
        self.step, self.key, self.problem = step, key, problem
        super().__init__(f"corrupt artifact {step}/{key[:12]}: {problem}")


def array_digest(a: np.ndarray) -> str:
    """sha256 of one array (dtype, shape, C-order bytes): checked each time the array is read."""
    import hashlib

    a = np.ascontiguousarray(a)
    h = hashlib.sha256(f"{a.dtype.str}|{a.shape}|".encode("utf-8"))
    h.update(a.tobytes())
    return h.hexdigest()

_TMP = ".tmp-"
#: The object that is an artifact on an object store (see the module docstring).
PACKED = "zarr.zip"
#: Bytes of a packed artifact a hit check reads: its attributes, and all of a small artifact
#: (which a `read` straight after the check then takes without another request).
_HEAD_BYTES = 64 * 1024
#: Whole small artifacts a hit check fetched, kept for the `read` that usually follows it.
_FETCHED = 8


def writer_tag() -> str:
    """`<host>-<pid>-<random>`: names a writer's temp (or object-store folder) so `gc` can tell
    a dead writer's leftovers from a live one's."""
    return f"{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


def _tag_writer(tag: str) -> tuple[str, int]:
    """(host, pid) from a `writer_tag`."""
    host, _, rest = tag.rpartition("-")[0].rpartition("-")
    return host, int(rest) if rest.isdigit() else -1


@lru_cache(maxsize=1)
def package_versions() -> dict[str, str]:
    """Versions recorded with every artifact, so a result can be traced to its software."""
    out = {}
    for name in ("embody", "numpy", "torch", "zarr", "mujoco", "pytorch-kinematics", "mannequin-x"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


@dataclass(frozen=True)
class Artifact:
    """A stored result: its arrays, the stage's own attrs and the store's bookkeeping (`info`)."""

    step: str
    key: str
    arrays: dict[str, np.ndarray]
    attrs: dict[str, Any]
    info: dict[str, Any]


def jsonable(value: Any) -> Any:
    """Attrs go to zarr.json: numpy scalars and arrays become plain JSON values."""
    def default(o: Any) -> Any:
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        return str(o)
    return json.loads(json.dumps(value, default=default))


def _real_dir(path: Path) -> bool:
    return path.is_dir() and not path.is_symlink()


def pid_alive(pid: int) -> bool:
    """Running on this host (a zombie waiting for its reaper counts as gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def store_location(text: str | Path) -> str | Path:
    """A store given as a path, `file://` URL or object-store URL: the local Path, or the URL;
    ConfigError for another scheme."""
    text = str(text)
    if text.startswith("file://"):
        from urllib.parse import unquote, urlparse

        url = urlparse(text)
        if url.netloc not in ("", "localhost"):
            raise ConfigError("run.store", f"a file:// store must be on this host, got {text!r}")
        return Path(unquote(url.path))
    if "://" in text:
        if not is_url(text):
            raise ConfigError("run.store", f"unsupported store URL {text!r}: use a local path, "
                              "file://, s3://, gs:// or az://")
        if not text.split("://", 1)[1].strip("/"):
            raise ConfigError("run.store", f"the store URL {text!r} names no bucket")
        return text.rstrip("/")
    return Path(text)


class ArtifactStore:
    """Content-addressed zarr artifacts on a local filesystem or an object store.

    `root` is the store's folder (a Path) or its URL (a str); `url` is either as text, what
    to hand to another process. Locations (`path`, `entries`, `stale_temps`) are Paths on a
    local store and URLs on an object store; `remove_path` and `size` take either.
    """

    def __init__(self, root: str | Path) -> None:
        where = store_location(root)
        self.objects: Objects | None = None
        if isinstance(where, str):
            self.objects = Objects(where)
            self._refs: dict[tuple[str, str], dict[str, Any]] = {}
            self._fetched: dict[tuple[str, str], bytes] = {}
            self.root: Any = where
            self.artifacts_dir = self.counters_dir = self.runs_dir = None  # type: ignore[assignment]
            return
        self.root = where.expanduser().resolve()
        self.artifacts_dir = self.root / "artifacts"
        self.counters_dir = self.root / "counters"
        self.runs_dir = self.root / "runs"

    @property
    def url(self) -> str:
        """The store as text: its absolute folder, or its URL."""
        return str(self.root)

    @property
    def is_local(self) -> bool:
        return self.objects is None

    def exists(self) -> bool:
        """The store's folder exists, or its prefix holds any object."""
        if self.objects is None:
            return self.root.is_dir()
        return bool(self.objects.children(""))

    # -- artifacts -------------------------------------------------------------------------
    def _base(self, step: str, key: str) -> str:
        return f"artifacts/{step}/{key[:2]}/{key}"

    def path(self, step: str, key: str) -> Any:
        """The artifact's folder (Path), or its URL on an object store."""
        if self.objects is not None:
            return f"{self.root}/{self._base(step, key)}"
        return self.artifacts_dir / step / key[:2] / key

    def has(self, step: str, key: str) -> bool:
        if self.objects is not None:
            self._refs.pop((step, key), None)
            try:
                self._ref(step, key)  # a ranged GET, not a HEAD: `intact`/`info`/`read` reuse it
            except (OSError, ValueError):
                return False
            return True
        return (self.path(step, key) / "zarr.json").is_file()

    def _remember(self, step: str, key: str, ref: dict[str, Any]) -> None:
        if len(self._refs) > 4096:
            self._refs.clear()
        self._refs[(step, key)] = ref

    def _ref(self, step: str, key: str) -> dict[str, Any]:
        """An object-store artifact's group attributes, read from its packed object's head
        (FileNotFoundError when there is none, ValueError when it is no packed group).
        A published object never changes (only `remove` deletes it), so this process keeps the
        last attributes it read or wrote; an artifact another process removed since is read as
        a corrupt one and recomputed, as a local group removed under a reader is."""
        assert self.objects is not None
        ref = self._refs.get((step, key))
        if ref is None:
            name = f"{self._base(step, key)}/{PACKED}"
            got = self.objects.get_head(name, _HEAD_BYTES)
            if got is None:
                raise FileNotFoundError(self.path(step, key))
            head, size = got
            first = packed.first_member(head)
            if isinstance(first, int):  # attributes longer than the head read
                got = self.objects.get_head(name, first)
                if got is None:
                    raise FileNotFoundError(self.path(step, key))
                head, size = got
                first = packed.first_member(head)
                if isinstance(first, int):
                    raise ValueError(f"{name}: shorter than its first member")
            member, written = first
            ref = {"attributes": json.loads(member).get("attributes", {}), "size": size,
                   "written": written}
            if len(head) == size:
                if len(self._fetched) >= _FETCHED:
                    self._fetched.clear()
                self._fetched[(step, key)] = head
            self._remember(step, key, ref)
        return ref

    def _encode(self, step: str, key: str, arrays: Mapping[str, np.ndarray],
                attrs: Mapping[str, Any], info: Mapping[str, Any]) -> dict[str, bytes]:
        """The zarr group's files (relative path → bytes), encoded in memory by zarr."""
        arrays = {name: np.ascontiguousarray(a) for name, a in arrays.items()}
        blobs: dict[str, Any] = {}
        group = zarr.open_group(store=zarr.storage.MemoryStore(blobs), mode="w", zarr_format=3)
        for name, a in arrays.items():
            arr = group.create_array(name, shape=a.shape, dtype=a.dtype,
                                     chunks=a.shape if a.ndim else (), overwrite=True)
            arr[...] = a
        # Chunk files and sizes as written (zarr skips all-fill chunks): `intact` checks
        # them. In path order (as the folder's sorted paths were listed before).
        files = {k: len(blobs[k]) for k in sorted(blobs, key=lambda k: k.split("/"))
                 if k.rsplit("/", 1)[-1] != "zarr.json"}
        group.attrs.update(jsonable({
            "embody": {**info, "step": step, "key": key, "status": "ok",
                       "checksum": arrays_checksum(arrays),
                       "digests": {n: array_digest(a) for n, a in arrays.items()},
                       "files": files, "versions": package_versions(),
                       "host": socket.gethostname(), "created": time.time()},
            "result": dict(attrs),
        }))
        return {rel: blobs[rel].to_bytes() for rel in sorted(blobs)}

    def publish(self, step: str, key: str, arrays: Mapping[str, np.ndarray],
                attrs: Mapping[str, Any], info: Mapping[str, Any]) -> bool:
        """Write an artifact atomically; False when another writer published the key first."""
        if self.objects is not None:
            return self._publish_object(step, key, arrays, attrs, info)
        final = self.path(step, key)
        if self.has(step, key):
            return False
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = final.parent / f"{key}{_TMP}{writer_tag()}"
        try:
            # zarr encodes the group into memory, then its files are written here: the same
            # bytes as zarr's LocalStore writes, without its thread hop and temp-file rename
            # per key (~11 → ~7 CPU-ms a publish, 2026-11-27); the group is still published
            # by one rename of its folder
            for rel, data in self._encode(step, key, arrays, attrs, info).items():
                path = tmp / rel
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
            os.rename(tmp, final)
            return True
        except OSError:
            if self.has(step, key):  # a concurrent writer won the rename
                return False
            raise
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    def _publish_object(self, step: str, key: str, arrays: Mapping[str, np.ndarray],
                        attrs: Mapping[str, Any], info: Mapping[str, Any]) -> bool:
        """Create the packed group with one create-only PUT: the one writer whose create
        succeeds has published; the others' PUTs are refused and leave nothing."""
        assert self.objects is not None
        blobs = self._encode(step, key, arrays, attrs, info)
        data = packed.pack(blobs)  # no `has` first: the create settles a race either way
        try:
            self.objects.put(f"{self._base(step, key)}/{PACKED}", data, create=True)
        except Conflict:
            return False
        self._remember(step, key, {"attributes": json.loads(blobs[packed.FIRST])["attributes"],
                                   "size": len(data), "written": len(data)})
        return True

    def info(self, step: str, key: str) -> dict[str, Any]:
        """The bookkeeping attrs of an artifact, read without opening its arrays."""
        return self._attributes(step, key).get("embody", {})

    def attrs(self, step: str, key: str) -> dict[str, Any]:
        """The stage's own attrs (what `read` returns as `attrs`), without opening the arrays."""
        return self._attributes(step, key).get("result", {})

    def _attributes(self, step: str, key: str) -> dict[str, Any]:
        """The group attributes in the artifact's `zarr.json` (bookkeeping and the stage's)."""
        if self.objects is not None:
            return self._ref(step, key).get("attributes", {})
        doc = json.loads((self.path(step, key) / "zarr.json").read_text())
        return doc.get("attributes", {})

    def intact(self, step: str, key: str) -> bool:
        """Cheap check (stat only) that every chunk file written is still there, same size
        (on an object store: that the packed object has the length it was written with, from
        the ranged GET `has` made).

        What a cache hit checks; `read` then checks each array's digest as it loads it.
        """
        if self.objects is not None:  # one object: its length is the one it was written with
            try:
                ref = self._ref(step, key)
            except (OSError, ValueError):
                return False
            return ref["size"] == ref["written"]
        try:
            files = self.info(step, key).get("files")
        except (OSError, ValueError):
            return False
        if files is None:  # written before files were recorded
            return True
        root = self.path(step, key)
        try:
            return all((root / rel).stat().st_size == size for rel, size in files.items())
        except OSError:
            return False

    def read(self, step: str, key: str, check: bool = True) -> Artifact:
        """The artifact's arrays and attrs; with `check`, CorruptArtifact when any array's
        bytes differ from its recorded digest (a deleted chunk reads as fill values)."""
        for attempt in range(2):
            try:
                group = self._group(step, key)
                arrays = {name: np.asarray(arr[...]) for name, arr in group.arrays()}
                attrs = dict(group.attrs)
                break
            except Exception as exc:  # unreadable metadata or chunk
                if attempt == 0 and self.objects is not None:
                    continue  # another process may have removed and republished it: once more
                if not check:
                    raise
                raise CorruptArtifact(step, key,
                                      f"unreadable: {type(exc).__name__}: {exc}") from None
        info = attrs.get("embody", {})
        if check:
            digests = info.get("digests")
            if digests is not None:
                if set(digests) != set(arrays):
                    raise CorruptArtifact(step, key, "arrays missing or added")
                for name, a in arrays.items():
                    if array_digest(a) != digests[name]:
                        raise CorruptArtifact(step, key, f"array {name!r} does not match its digest")
            elif info.get("checksum") and arrays_checksum(arrays) != info["checksum"]:
                raise CorruptArtifact(step, key, "checksum mismatch")
        return Artifact(step, key, arrays, attrs.get("result", {}), info)

    def _group(self, step: str, key: str) -> Any:
        """The artifact's zarr group, opened read-only (an object store's in memory, from the
        one GET of its packed object, or from the hit check that fetched it whole just now)."""
        if self.objects is None:
            return zarr.open_group(str(self.path(step, key)), mode="r")
        data = self._fetched.pop((step, key), None)
        if data is None:
            got = self.objects.get(f"{self._base(step, key)}/{PACKED}")
            if got is None:
                self._refs.pop((step, key), None)
                raise FileNotFoundError(self.path(step, key))
            data = got[0]
        from zarr.core.buffer import default_buffer_prototype

        wrap = default_buffer_prototype().buffer.from_bytes
        files = {rel: wrap(blob) for rel, blob in packed.unpack(data).items()}
        return zarr.open_group(store=zarr.storage.MemoryStore(files, read_only=True), mode="r",
                               zarr_format=3)

    def entries(self) -> Iterator[tuple[str, str, Any]]:
        """Every published artifact as (step, key, location); temps are skipped."""
        if self.objects is not None:
            found = set()
            for meta in self.objects.list("artifacts"):
                parts = meta["path"].split("/")
                if len(parts) == 5 and parts[4] == PACKED and parts[2] == parts[3][:2]:
                    found.add((parts[1], parts[3]))
            for step, key in sorted(found):
                yield step, key, self.path(step, key)
            return
        if not _real_dir(self.artifacts_dir):
            return
        for step_dir in sorted(p for p in self.artifacts_dir.iterdir() if _real_dir(p)):
            for prefix in sorted(p for p in step_dir.iterdir() if _real_dir(p)):
                for path in sorted(prefix.iterdir()):
                    if _TMP not in path.name and _real_dir(path) and (path / "zarr.json").is_file():
                        yield step_dir.name, path.name, path

    def verify(self, step: str, key: str) -> str | None:
        """Re-hash an artifact's arrays; the problem in one line, or None when intact."""
        try:
            art = self.read(step, key, check=False)
        except Exception as exc:  # any unreadable chunk or metadata is corruption
            return f"unreadable: {type(exc).__name__}: {exc}"
        expected = art.info.get("checksum")
        if expected is None:
            return "no checksum recorded"
        if arrays_checksum(art.arrays) != expected:
            return "checksum mismatch"
        return None

    def remove(self, step: str, key: str) -> None:
        if self.objects is not None:
            self._refs.pop((step, key), None)
            self._fetched.pop((step, key), None)
            self.objects.delete([f"{self._base(step, key)}/{PACKED}"])
            return
        self.remove_path(self.path(step, key))

    def _relative(self, where: Any) -> str:
        """An object-store location (URL) relative to the store; ValueError outside it."""
        text = str(where)
        if not text.startswith(f"{self.root}/") or ".." in text.split("/"):
            raise ValueError(f"refusing to delete {text}: not inside the store {self.root}")
        return text[len(str(self.root)) + 1:].strip("/")

    def size(self, where: Any) -> int:
        """Bytes under a location (an artifact, a temp) of the store."""
        if self.objects is not None:
            return sum(int(o["size"]) for o in self.objects.list(self._relative(where)))
        path = Path(where)
        if path.is_dir() and not path.is_symlink():
            return sum(p.lstat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())
        return path.lstat().st_size if path.exists() or path.is_symlink() else 0

    def remove_path(self, path: Any) -> None:
        """Delete a file or folder of the store; never through a symlink, never outside."""
        if self.objects is not None:
            parts = self._relative(path).split("/")
            if len(parts) == 4 and parts[0] == "artifacts":
                self.remove(parts[1], parts[3])
            else:  # the object of that name and any below it as a folder
                rel = "/".join(parts)
                self.objects.delete([rel, *(o["path"] for o in self.objects.list(rel))])
            return
        if not self.contains(path):
            raise ValueError(f"refusing to delete {path}: not inside the store {self.root}")
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)

    def contains(self, path: Any) -> bool:
        """`path` lies inside the store and no component below the root is a symlink."""
        if self.objects is not None:
            try:
                return bool(self._relative(path))
            except ValueError:
                return False
        path = Path(os.path.abspath(path))
        try:
            rel = path.relative_to(self.root)
        except ValueError:
            return False
        probe = self.root
        for part in rel.parts:
            probe = probe / part
            if probe.is_symlink():
                return False
        return path.resolve().is_relative_to(self.root)

    def stale_temps(self, max_age_s: float = 24 * 3600) -> list[Any]:
        """Temps of writers that died (same host, PID gone) or are older than `max_age_s`:
        artifact groups and manifest temps (`runs/<run>/.manifest.json.<pid>.tmp`)."""
        host, now, out = socket.gethostname(), time.time(), []
        if self.objects is not None:
            return self._strays(max_age_s)
        if _real_dir(self.runs_dir):
            for path in self.runs_dir.glob("*/.*.tmp"):
                pid = path.name.rsplit(".", 2)[-2]
                dead = not (pid.isdigit() and pid_alive(int(pid)))
                if self.contains(path) and (dead or now - path.lstat().st_mtime > max_age_s):
                    out.append(path)
        if not _real_dir(self.artifacts_dir):
            return out
        for path in self.artifacts_dir.glob(f"*/*/*{_TMP}*"):
            if not self.contains(path):
                continue
            t_host, pid = _tag_writer(path.name.split(_TMP, 1)[1])
            dead = t_host == host and not pid_alive(pid)
            if dead or now - path.stat().st_mtime > max_age_s:
                out.append(path)
        return out

    def _strays(self, max_age_s: float) -> list[str]:
        """Object store: what lies in an artifact's folder besides its packed object (no writer
        of this store leaves anything: a PUT lands whole or not at all; this is another tool's
        or layout's upload), by the first name below the key, once its newest object is
        `max_age_s` old."""
        assert self.objects is not None
        newest: dict[str, float] = {}
        for meta in self.objects.list("artifacts"):
            parts = meta["path"].split("/")
            if len(parts) < 5 or (len(parts) == 5 and parts[4] == PACKED):
                continue
            where = "/".join(parts[:5])
            newest[where] = max(newest.get(where, 0.0), mtime(meta))
        now = time.time()
        return [f"{self.root}/{where}" for where, t in sorted(newest.items())
                if now - t >= max_age_s]

    # -- runs ------------------------------------------------------------------------------
    def manifest_path(self, run: str) -> Any:
        """Where a run's manifest lives: a Path, or its URL on an object store."""
        if self.objects is not None:
            return f"{self.root}/runs/{run}/manifest.json"
        return self.runs_dir / run / "manifest.json"

    def read_manifest_text(self, run: str) -> str | None:
        """A run's manifest as text; None when there is none (OSError when unreadable)."""
        if self.objects is not None:
            got = self.objects.get(f"runs/{run}/manifest.json")
            return None if got is None else got[0].decode("utf-8")
        path = self.manifest_path(run)
        return path.read_text(encoding="utf-8") if path.is_file() else None

    def manifest_mtime(self, run: str) -> float:
        """When a run's manifest was last written (epoch seconds)."""
        if self.objects is not None:
            meta = self.objects.head(f"runs/{run}/manifest.json")
            if meta is None:
                raise FileNotFoundError(self.manifest_path(run))
            return mtime(meta)
        return self.manifest_path(run).stat().st_mtime

    @property
    def work_dir(self) -> Path:
        """A local folder for what must live on this machine's disk beside the store (Prefect's
        home, a generated dataset): the store's own folder, or, for an object store,
        `$EMBODY_WORK_DIR` else `~/.cache/embody/<bucket-prefix>-<hash>`."""
        if self.objects is None:
            return self.root
        import hashlib
        import re

        base = os.environ.get("EMBODY_WORK_DIR") or Path("~/.cache/embody").expanduser()
        name = re.sub(r"[^A-Za-z0-9_.-]+", "-", self.root.split("://", 1)[1]).strip("-.")[:60]
        digest = hashlib.sha256(self.root.encode("utf-8")).hexdigest()[:8]
        return Path(base).expanduser().resolve() / f"{name}-{digest}"

    def write_run_file(self, run: str, name: str, data: bytes) -> Any:
        """Write `runs/<run>/<name>` (e.g. `sequences.csv`) whole, atomically; its location."""
        if self.objects is not None:
            self.objects.put(f"runs/{run}/{name}", data)
            return f"{self.root}/runs/{run}/{name}"
        path = self.runs_dir / run / name
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{name}.{os.getpid()}.tmp")
        try:
            tmp.write_bytes(data)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return path

    def run_names(self) -> list[str]:
        """The runs that have a manifest, by name."""
        if self.objects is not None:
            names = {o["path"].split("/")[1] for o in self.objects.list("runs")
                     if o["path"].count("/") == 2 and o["path"].endswith("/manifest.json")}
            return sorted(names)
        if not self.runs_dir.is_dir():
            return []
        return sorted(p.parent.name for p in self.runs_dir.glob("*/manifest.json"))

    # -- counters --------------------------------------------------------------------------
    def record(self, step: str, key: str, **fields: Any) -> None:
        """Append one computation line; a single O_APPEND write keeps concurrent lines whole
        (on an object store, which cannot append, one object per line)."""
        if self.objects is not None:
            line = json.dumps({"step": step, "key": key, "time": time.time(), "pid": os.getpid(),
                               **fields}, sort_keys=True, default=str)
            name = f"{time.time_ns():020d}-{writer_tag()}.json"
            self.objects.put(f"counters/{step}/{name}", line.encode("utf-8"))
            return
        self.counters_dir.mkdir(parents=True, exist_ok=True)
        line = json.dumps({"step": step, "key": key, "time": time.time(), "pid": os.getpid(),
                           **fields}, sort_keys=True, default=str) + "\n"
        fd = os.open(self.counters_dir / f"{step}.jsonl", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            os.write(fd, line.encode("utf-8"))
        finally:
            os.close(fd)

    def computations(self, step: str | None = None) -> list[dict[str, Any]]:
        """Every recorded computation (of one step, or all), oldest first."""
        if self.objects is not None:
            keys = [o["path"] for o in self.objects.list(f"counters/{step}" if step else "counters")]
            blobs = self.objects.get_many(keys)
            return sorted((json.loads(blobs[k]) for k in keys if k in blobs),
                          key=lambda r: r["time"])
        if not self.counters_dir.is_dir():
            return []
        files = [self.counters_dir / f"{step}.jsonl"] if step else sorted(self.counters_dir.glob("*.jsonl"))
        rows = []
        for f in files:
            if f.is_file():
                rows += [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
        return sorted(rows, key=lambda r: r["time"])
