"""A robot's MJCF compiled by MuJoCo once, kept as MJB (MuJoCo's binary model) in embody's cache.

Compiling the default G1's MJCF takes ~0.9 s (its STL meshes are read and their convex hulls
built), in every process that loads the robot: each run, each test process. The compiled model
is cached under a key of the MuJoCo version and the path, size and modification time of the MJCF
and of every file beside it (meshes, includes), so any edit recompiles; loading the MJB is
exact (MuJoCo's own serialisation) and takes milliseconds.

Every model handed out has MuJoCo's `vis.global.bvactive` off: with it on (MuJoCo's default)
each `mj_collision` call (so each `mj_step`, `mj_forward` and `mj_inverse`) first clears one
byte per mesh BVH node for the viewer's bounding-volume display, 1.26 M bytes on the G1 with
hands: more than half of a fixed-base replay step and three quarters of an `mj_inverse`, even
with contacts disabled. Nothing in the dynamics reads those bytes.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Callable

import mujoco

from embody.cache import cache_dir

__all__ = ["compiled_model", "model_key"]


def model_key(mjcf: Path) -> str:
    """What the compiled model depends on, as stats (not bytes: the G1 folder holds 38 MB)."""
    folder = mjcf.resolve().parent
    stats = [f"{p.relative_to(folder)}:{s.st_size}:{s.st_mtime_ns}"
             for p in sorted(folder.rglob("*")) if p.is_file() for s in (p.stat(),)]
    blob = "\n".join([mujoco.__version__, str(mjcf.resolve()), *stats])
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def cached_model(name: str, build: Callable[[], mujoco.MjModel]) -> mujoco.MjModel:
    """The model cached as `<cache>/mujoco/<name>.mjb`, else `build()`'s, saved there (a temp
    file renamed into place; a read-only cache only costs the build); `bvactive` off."""
    path = cache_dir() / "mujoco" / f"{name}.mjb"
    if path.is_file():
        try:
            return _without_bvh_marks(mujoco.MjModel.from_binary_path(str(path)))
        except (ValueError, OSError):
            pass  # unreadable (another MuJoCo build, a torn file): build again
    model = _without_bvh_marks(build())
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        mujoco.mj_saveModel(model, str(tmp), None)
        os.replace(tmp, path)
    except OSError:
        pass
    return model


def _without_bvh_marks(model: mujoco.MjModel) -> mujoco.MjModel:
    model.vis.global_.bvactive = 0
    return model


def compiled_model(mjcf: str | Path) -> mujoco.MjModel:
    """`MjModel.from_xml_path(mjcf)`, from the cache when it holds this model (ValueError from
    MuJoCo when the MJCF does not compile, as from `from_xml_path`)."""
    mjcf = Path(mjcf)
    return cached_model(f"{mjcf.stem}-{model_key(mjcf)}",
                        lambda: mujoco.MjModel.from_xml_path(str(mjcf)))
