"""Lazy datasets: a folder of motion files, a SOKE root with a split, or a CSV manifest.

Listing touches only names, never contents, so one bad file fails only its own `load()`.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from embody.config.io import IOConfig
from embody.errors import InputError
from embody.io import soke
from embody.io.loader import MOTION_SUFFIXES, load
from embody.io.remote import fetch_dataset, is_url, url_of
from embody.motion import Motion


@dataclass(frozen=True)
class SequenceRef:
    """One sequence of a dataset: a stable id, where it lives, and its text if known."""

    id: str
    path: Path
    text: str | None = None
    source_files: tuple[Path, ...] = ()

    def load(self, fps: float | None = None, up_axis: str | None = None,
             hands: str | None = None, limits: IOConfig | None = None) -> Motion:
        """The motion; `fps`/`up_axis`/`hands` override the file's (see `embody.io.load`),
        within `limits` (the `io` config; defaults if None)."""
        motion = load(self.path, fps=fps, up_axis=up_axis, hands=hands, limits=limits)
        motion.meta.setdefault("id", self.id)
        if self.text is not None:
            motion.meta["text"] = self.text
        return motion


class Dataset:
    """An ordered, sized collection of `SequenceRef`s with unique ids."""

    def __init__(self, root: Path, refs: list[SequenceRef], kind: str,
                 where: list[str] | None = None, origin: Path | None = None) -> None:
        """`where` names each ref's place in `origin` (a CSV line) for the duplicate-id error."""
        self._by_id: dict[str, SequenceRef] = {}
        first: dict[str, int] = {}
        for i, ref in enumerate(refs):
            if ref.id in self._by_id:
                at = (f" ({where[i]}; first on {where[first[ref.id]]})" if where else "")
                raise InputError(origin or root, "id", f"duplicate sequence id {ref.id!r}{at}")
            first[ref.id] = i
            self._by_id[ref.id] = ref
        self.root = root
        self.kind = kind
        self._refs = tuple(refs)

    def __len__(self) -> int:
        return len(self._refs)

    def __iter__(self) -> Iterator[SequenceRef]:
        return iter(self._refs)

    def __getitem__(self, index: int) -> SequenceRef:
        return self._refs[index]

    @property
    def ids(self) -> list[str]:
        return [r.id for r in self._refs]

    def get(self, seq_id: str) -> SequenceRef:
        """The sequence with id `seq_id` (KeyError if absent)."""
        return self._by_id[seq_id]

    def __repr__(self) -> str:
        return f"Dataset({self.kind}, {self.root}, {len(self)} sequences)"


def _folder(root: Path) -> Dataset:
    """Every motion file below `root` is one sequence (SOKE data goes through its root)."""
    refs: list[SequenceRef] = []
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if any(part.startswith(".") for part in rel.parts) or not path.is_file():
            continue
        if path.suffix.lower() in MOTION_SUFFIXES:
            refs.append(SequenceRef(rel.with_suffix("").as_posix(), path, None, (path,)))
    return Dataset(root, refs, "folder")


def _inside(base: Path, target: Path) -> bool:
    """Whether `target` resolves (symlinks and `..` followed) inside `base`."""
    try:
        target.resolve().relative_to(base.resolve())
    except ValueError:
        return False
    return True


def _soke(root: Path, split: str | None, limits: IOConfig) -> Dataset:
    poses = root / "poses"
    if split is None:
        names = sorted(p.name for p in poses.iterdir() if p.is_dir())
        entries = [{"name": n} for n in names]
    else:
        entries = soke.read_split(root, split)
    refs = []
    for entry in entries:
        name = str(entry["name"])
        folder = poses / name
        if not limits.allow_outside_paths and (not name or Path(name).is_absolute()
                                               or ".." in Path(name).parts
                                               or not _inside(poses, folder)):
            raise InputError(root / f"csl_clean.{split}", "name",
                             f"{name!r} points outside poses/ (set io.allow_outside_paths=true "
                             "to allow)")
        folder = folder.absolute()
        text = entry.get("text")
        # frame files are listed on load: listing 20k folders up front costs minutes
        refs.append(SequenceRef(str(entry["name"]), folder, None if text is None else str(text),
                                (folder,)))
    return Dataset(root, refs, f"soke-{split}" if split else "soke")


def _manifest(path: Path, limits: IOConfig) -> Dataset:
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(path, None, f"cannot read CSV manifest: {exc}") from None
    if not rows or "path" not in rows[0]:
        raise InputError(path, "path", "manifest needs a header 'path,text' and at least one row")
    refs, where = [], []
    for i, row in enumerate(rows, start=2):
        rel = (row.get("path") or "").strip()
        if not rel:
            raise InputError(path, "path", f"empty path on line {i}")
        target = Path(rel) if Path(rel).is_absolute() else path.parent / rel
        if not limits.allow_outside_paths and not _inside(path.parent, target):
            raise InputError(path, "path", f"line {i}: {rel!r} is outside the manifest's folder "
                                           "(set io.allow_outside_paths=true to allow)")
        target = target.absolute()
        text = row.get("text")
        refs.append(SequenceRef(Path(rel).with_suffix("").as_posix(), target,
                                text if text else None, (target,)))
        where.append(f"line {i}")
    return Dataset(path.parent, refs, "manifest", where, path)


def load_dataset(path: str | Path, split: str | None = None,
                 limits: IOConfig | None = None) -> Dataset:
    """A lazy dataset from a folder, a SOKE root (+ `split`), or a `path,text` CSV manifest;
    any of them at an object-store URL too (`embody.io.remote`).

    `limits` (the `io` config) decides whether split names and manifest paths may point
    outside the dataset's folder; loads use it through `SequenceRef.load(limits)`.
    """
    limits = limits or IOConfig()
    if is_url(str(path)):  # s3://, gs://, az://: read from its local mirror
        local = fetch_dataset(str(path))
        try:
            return load_dataset(local, split, limits)
        except InputError as exc:
            raise url_of(exc, local, str(path)) from None
    path = Path(path)
    if not path.exists():
        raise InputError(path, None, "no such file or directory")
    if path.is_file():
        if path.suffix.lower() != ".csv":
            raise InputError(path, None, "a dataset is a folder or a .csv manifest")
        if split is not None:
            raise InputError(path, "split", "splits apply to SOKE roots only")
        return _manifest(path, limits)
    poses = path / "poses"
    if poses.is_dir() and (split is not None or any(p.is_dir() for p in poses.iterdir())):
        return _soke(path, split, limits)
    if split is not None:
        raise InputError(path, "split", f"no csl_clean.{split} and poses/ here (not a SOKE root)")
    dataset = _folder(path)
    if not len(dataset):
        raise InputError(path, None, "no motion files found")
    return dataset
