"""Every benchmark the docs name exists and answers `--help`; benchmarks/ holds only listed scripts.

Why: a figure in the README or docs/ is only as good as the command that prints it, and a script
nobody lists is an experiment nobody will rerun. `benchmarks/physics.py` is planned (issue 35):
listed before it lands, so it may be absent.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
PLANNED = {"physics"}


def named_in(text: str) -> set[str]:
    """Script names (without `.py`) that a document refers to as `benchmarks/<name>.py`."""
    return set(re.findall(r"benchmarks/([A-Za-z0-9_]+)\.py", text))


def listed_in_readme() -> set[str]:
    """Scripts benchmarks/README.md lists: the first column of its table (`name.py ...`)."""
    text = (BENCH / "README.md").read_text()
    return set(re.findall(r"(?m)^\| `([A-Za-z0-9_]+)\.py\b", text))


def docs_names() -> set[str]:
    docs = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), BENCH / "README.md"]
    return set().union(*(named_in(d.read_text()) for d in docs)) | listed_in_readme()


def test_readme_lists_the_headline_benchmarks():
    listed = listed_in_readme()
    for name in ("collision", "ik_vs_mink", "fidelity", "pipeline", "scale", "memory",
                 "export_check", "gpu", "orchestration", "physics"):
        assert name in listed, f"benchmarks/README.md does not list {name}.py"


def test_benchmarks_folder_holds_only_listed_scripts():
    present = {p.stem for p in BENCH.glob("*.py")}
    unlisted = present - listed_in_readme()
    assert not unlisted, f"benchmarks/ scripts not listed in benchmarks/README.md: {sorted(unlisted)}"


def test_every_named_benchmark_exists_and_answers_help():
    names = sorted(docs_names())
    missing = [n for n in names if not (BENCH / f"{n}.py").exists() and n not in PLANNED]
    assert not missing, f"docs name benchmarks that do not exist: {missing}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    runs = {n: subprocess.Popen([sys.executable, str(BENCH / f"{n}.py"), "--help"], cwd=ROOT, env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            for n in names if (BENCH / f"{n}.py").exists()}
    failed = {}
    for name, proc in runs.items():
        out, _ = proc.communicate(timeout=600)
        if proc.returncode != 0 or "usage:" not in out:
            failed[name] = (proc.returncode, out[-500:])
    assert not failed, f"`--help` failed: {failed}"
