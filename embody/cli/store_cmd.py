"""`embody store ls|verify|gc`: inspect, check and clean the artifact store."""

from __future__ import annotations

import shutil
from collections import defaultdict
from typing import Any

import click

from embody.verdicts import plural

from embody.cli.common import emit_json, json_option

_store_option = click.option("--store", "store_dir", default="embody-store", show_default=True,
                             help="Artifact store: a directory, or s3://bucket/prefix "
                                  "(gs://, az://, file://).")


def _open(store_dir: str) -> Any:
    from embody.store import ArtifactStore
    from embody.errors import InputError

    store = ArtifactStore(store_dir)
    if not store.exists():
        raise InputError(store.root, None, "no such store directory" if store.is_local
                         else "no store there (no objects under this URL)")
    return store


@click.group("store")
def command() -> None:
    """Inspect (ls), check (verify) and clean (gc) the artifact store."""


@command.command("ls")
@_store_option
@json_option
def ls(store_dir: str, as_json: bool) -> int:
    """Artifacts per step (count, size) and the runs with their sequence status."""
    from embody.store import load_manifests

    store = _open(store_dir)
    steps: dict[str, dict[str, int]] = defaultdict(lambda: {"artifacts": 0, "bytes": 0})
    for step, _key, path in store.entries():
        steps[step]["artifacts"] += 1
        steps[step]["bytes"] += store.size(path)
    runs = {}
    for m in load_manifests(store):
        status = [s["status"] for s in m.sequences.values()]
        runs[m.run] = {"sequences": len(status), "ok": status.count("ok"),
                       "failed": status.count("failed"), "pending": status.count("pending"),
                       "finished": m.data.get("finished") is not None}
    if as_json:
        emit_json({"store": str(store.root), "steps": dict(steps), "runs": runs})
        return 0
    click.echo(f"store {store.root}")
    for step, c in sorted(steps.items()):
        click.echo(f"  {step:<12} {c['artifacts']:>7} {'artifact ' if c['artifacts'] == 1 else 'artifacts'} {c['bytes'] / 1e6:>10.2f} MB")
    for run, r in sorted(runs.items()):
        state = "finished" if r["finished"] else "unfinished"
        click.echo(f"  run {run}: {r['ok']}/{r['sequences']} ok, {r['failed']} failed ({state})")
    return 0


@command.command("verify")
@_store_option
@json_option
def verify(store_dir: str, as_json: bool) -> int:
    """Re-hash every artifact's arrays; exit 1 when any group is corrupt."""
    store = _open(store_dir)
    checked, corrupt = 0, []
    for step, key, path in store.entries():
        checked += 1
        problem = store.verify(step, key)
        if problem:
            corrupt.append({"step": step, "key": key, "path": str(path), "problem": problem})
    if as_json:
        emit_json({"checked": checked, "corrupt": corrupt})
    else:
        for c in corrupt:
            click.echo(f"CORRUPT {c['step']}/{c['key']}: {c['problem']}")
        click.echo(f"{plural(checked, 'artifact')} checked, {len(corrupt)} corrupt")
    return 1 if corrupt else 0


def _duration(text: str) -> float:
    """Seconds from `90`, `90s`, `30m`, `12h` or `7d`."""
    import re

    from embody.errors import UsageError

    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([smhd]?)\s*", text or "")
    if not m:
        raise UsageError(f"--older-than: expected a duration like 90s, 30m, 12h or 7d, got {text!r}")
    return float(m.group(1)) * {"": 1, "s": 1, "m": 60, "h": 3600, "d": 86400}[m.group(2)]


@command.command("gc")
@_store_option
@click.option("--dry-run", is_flag=True, help="Only list what would be removed.")
@click.option("--older-than", "older_than", default=None, metavar="DURATION",
              help="Treat unfinished runs whose manifest is older than this (e.g. 12h, 7d) as "
                   "abandoned: only what their manifest records is kept.")
@json_option
def gc(store_dir: str, dry_run: bool, older_than: str | None, as_json: bool) -> int:
    """Remove artifacts no run references, and temps of dead writers.

    A run without a `finished` stamp (in progress, or killed) is live: every artifact it
    computed is kept, recorded in its manifest or not, unless `--older-than` says it is
    abandoned. Symlinks are never followed out of the store.
    """
    import time

    from embody.store import load_manifests

    store = _open(store_dir)
    max_age = _duration(older_than) if older_than is not None else None
    referenced: set[tuple[str, str]] = set()
    live: list[str] = []
    for m in load_manifests(store):
        referenced |= m.keys()
        if not m.finished:
            age = time.time() - m.modified()
            if max_age is None or age < max_age:
                live.append(m.run)

    def owned_by_live_run(step: str, key: str) -> bool:
        if not live:
            return False
        try:
            return store.info(step, key).get("run") in live
        except (OSError, ValueError):
            return True  # unreadable: not ours to judge here (`store verify` reports it)

    doomed = [(step, key, path) for step, key, path in store.entries()
              if (step, key) not in referenced and not owned_by_live_run(step, key)]
    temps = store.stale_temps()
    freed = sum(store.size(p) for _, _, p in doomed) + sum(store.size(p) for p in temps)
    if not dry_run:
        for _step, _key, path in doomed:
            store.remove_path(path)
        for path in temps:
            store.remove_path(path)
    removed = [{"step": s, "key": k} for s, k, _ in doomed]
    if as_json:
        emit_json({"dry_run": dry_run, "removed": removed, "temps": [str(p) for p in temps],
                   "kept": len(referenced), "live_runs": live, "bytes": freed})
    else:
        verb = "would remove" if dry_run else "removed"
        for r in removed:
            click.echo(f"{verb} {r['step']}/{r['key']}")
        for run in live:
            click.echo(f"kept every artifact of unfinished run {run} "
                       "(in progress or killed; --older-than overrides)")
        click.echo(f"{verb} {plural(len(removed), 'artifact')} and {plural(len(temps), 'stale temp')} "
                   f"({freed / 1e6:.2f} MB); {len(referenced)} referenced")
    return 0
