"""The installed layout: `embody` is the only top-level package (`tasks/`, `flows/` and `store/`
ship inside it as `embody.tasks`, `embody.flows`, `embody.store`), so no other package named
`tasks`, `flows` or `store` can break embody or be broken by it."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_SKIP = shutil.ignore_patterns(".venv", "venv", ".git", "embody-store", "reports", "build", "dist",
                               "*.egg-info", "__pycache__", ".pytest_cache", "data")


def test_wheel_has_embody_as_its_only_top_level_package(tmp_path: Path) -> None:
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, symlinks=True, ignore=_SKIP)
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                           "-q", str(src), "-w", str(tmp_path / "dist")],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("embody-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top == {"embody"}
    for sub in ("tasks/stages.py", "flows/dataset.py", "store/artifacts.py", "configs/default.yaml"):
        assert f"embody/{sub}" in names, sub


def test_no_module_imports_the_old_top_level_names() -> None:
    """Every import of the orchestration packages goes through `embody.` (a bare `import tasks`
    would only work from a source checkout)."""
    import re

    bad = re.compile(r"^\s*(from|import)\s+(tasks|flows|store)(\.|\s|$)", re.M)
    offenders = [str(p.relative_to(ROOT)) for d in ("embody", "tasks", "flows", "store", "tests",
                                                    "benchmarks", "scripts")
                 for p in (ROOT / d).rglob("*.py")
                 if bad.search(p.read_text())]
    assert offenders == []
