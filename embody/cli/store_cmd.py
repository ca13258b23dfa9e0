"""`embody store ls|verify|gc`: inspect, check and clean the artifact store."""

from __future__ import annotations

import shutil
from collections import defaultdict
from pathlib import Path
from typing import Any

import click

from embody.verdicts import plural

from embody.cli.common import emit_json, json_option

_store_option = click.option("--store", "store_dir", default="embody-store", show_default=True,
                             type=click.Path(file_okay=False), help="Artifact store directory.")


def _open(store_dir: str) -> Any:
    from store import ArtifactStore
    from embody.errors import InputError

    store = ArtifactStore(store_dir)
    if not store.root.is_dir():
        raise InputError(store.root, None, "no such store directory")
    return store


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


@click.group("store")
def command() -> None:
    """Inspect (ls), check (verify) and clean (gc) the artifact store."""


@command.command("ls")
@_store_option
@json_option
def ls(store_dir: str, as_json: bool) -> int:
    """Artifacts per step (count, size) and the runs with their sequence status."""
    from store import load_manifests

    store = _open(store_dir)
    steps: dict[str, dict[str, int]] = defaultdict(lambda: {"artifacts": 0, "bytes": 0})
    for step, _key, path in store.entries():
        steps[step]["artifacts"] += 1
        steps[step]["bytes"] += _size(path)
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


@command.command("gc")
@_store_option
@click.option("--dry-run", is_flag=True, help="Only list what would be removed.")
@json_option
def gc(store_dir: str, dry_run: bool, as_json: bool) -> int:
    """Remove artifacts no run manifest references, and temps of dead writers.

    Do not run it while a run is in progress: its newest artifacts are not in a manifest yet.
    """
    from store import load_manifests

    store = _open(store_dir)
    referenced: set[tuple[str, str]] = set()
    for m in load_manifests(store):
        referenced |= m.keys()
    doomed = [(step, key, path) for step, key, path in store.entries()
              if (step, key) not in referenced]
    temps = store.stale_temps()
    freed = sum(_size(p) for _, _, p in doomed) + sum(_size(p) for p in temps)
    if not dry_run:
        for _step, _key, path in doomed:
            shutil.rmtree(path, ignore_errors=True)
        for path in temps:
            shutil.rmtree(path, ignore_errors=True)
    removed = [{"step": s, "key": k} for s, k, _ in doomed]
    if as_json:
        emit_json({"dry_run": dry_run, "removed": removed, "temps": [str(p) for p in temps],
                   "kept": len(referenced), "bytes": freed})
    else:
        verb = "would remove" if dry_run else "removed"
        for r in removed:
            click.echo(f"{verb} {r['step']}/{r['key']}")
        click.echo(f"{verb} {plural(len(removed), 'artifact')} and {plural(len(temps), 'stale temp')} "
                   f"({freed / 1e6:.2f} MB); {len(referenced)} referenced")
    return 0
