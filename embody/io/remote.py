"""Datasets at object-store URLs (`s3://bucket/prefix`, `gs://`, `az://`), mirrored locally.

A dataset URL names a prefix (a folder of motion files, or a SOKE root) or a `.csv` manifest
object. Its objects are copied once into a local mirror and the dataset is read from there, so
every reader (the formats' loaders, the limits, the content keys from file bytes) works as on a
local folder and the worker processes never touch the object store (obstore's client does not
survive `fork`). A rerun fetches only objects whose ETag changed. Errors name the object's URL.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from embody.errors import InputError
from embody.store.objects import Objects, is_url

__all__ = ["fetch_dataset", "is_url", "mirror_dir", "url_of"]



def mirror_dir(url: str) -> Path:
    """Where `url` is mirrored: `$EMBODY_WORK_DIR/datasets/<hash>/<last name>` (default
    `~/.cache/embody/...`), so the folder keeps the dataset's own name (the run's default name)."""
    url = url.rstrip("/")
    base = Path(os.environ.get("EMBODY_WORK_DIR") or "~/.cache/embody").expanduser()
    digest = hashlib.sha256(url.encode("utf-8")).hexdigest()[:12]
    name = url.rsplit("/", 1)[-1] if url.count("/") > 2 else "dataset"
    return base.resolve() / "datasets" / digest / (name or "dataset")


def url_of(error: InputError, local: Path, url: str) -> InputError:
    """`error` about a file of the mirror at `local`, naming the object's URL instead."""
    try:
        rel = Path(error.path).resolve().relative_to(local.resolve()).as_posix()
    except ValueError:
        return error
    where = url.rstrip("/") if rel == "." else f"{url.rstrip('/')}/{rel}"
    return InputError(where, error.field, error.message)


def fetch_dataset(url: str) -> Path:
    """The local mirror of the dataset at `url` (a folder, or the manifest's file in it),
    brought up to date; InputError (naming `url`) when there is nothing there or it cannot be
    read."""
    url = url.rstrip("/")
    rest = url.partition("://")[2]
    if "/" not in rest.strip("/"):
        raise InputError(url, None, "a dataset URL names a prefix or object below the bucket")
    local = mirror_dir(url)
    try:
        listed = list(Objects(url).list(""))
        if listed:
            _sync(Objects(url), listed, local)
            return local
        parent, _, name = url.rpartition("/")
        meta = Objects(parent).head(name)
        if meta is None:
            raise InputError(url, None, "no such object or prefix")
        if not name.lower().endswith(".csv"):
            raise InputError(url, None, "a dataset is a prefix (folder) or a .csv manifest")
        # a manifest names its files relative to itself: mirror its folder beside it
        _sync(Objects(parent), list(Objects(parent).list("")), local.parent)
        return local.parent / name
    except InputError:
        raise
    except Exception as exc:  # credentials, network, a bucket that is not there
        raise InputError(url, None, f"cannot be read: {type(exc).__name__}: {exc}") from None


def _sync(objects: Objects, listed: list[dict], local: Path) -> None:
    """Copy what changed (by ETag) of `listed` below `local`; drop files no longer listed."""
    index_path = local.with_name(f"{local.name}.mirror.json")  # object path → ETag
    try:
        held = json.loads(index_path.read_text())
    except (OSError, ValueError):
        held = {}
    wanted = {m["path"]: m.get("e_tag") or str(m.get("size")) for m in listed}
    stale = [p for p, tag in wanted.items()
             if held.get(p) != tag or not (local / p).is_file()]
    for rel in stale:
        if ".." in rel.split("/"):
            raise InputError(f"{objects.url}/{rel}", None, "an object name with '..'")
    fetched = objects.get_many(stale)
    for rel in stale:
        if rel not in fetched:
            raise InputError(f"{objects.url}/{rel}", None, "removed while being read")
        path = local / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_bytes(fetched[rel])
        os.replace(tmp, path)
    for rel in set(held) - set(wanted):
        (local / rel).unlink(missing_ok=True)
    local.mkdir(parents=True, exist_ok=True)
    tmp = index_path.with_name(f".{index_path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(wanted, sort_keys=True))
    os.replace(tmp, index_path)
