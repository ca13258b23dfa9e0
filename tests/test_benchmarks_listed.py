"""Every benchmark the docs name exists and answers `--help`; benchmarks/ holds only listed scripts.

Why: a figure in the README or docs/ is only as good as the command that prints it, and a script
nobody lists is an experiment nobody will rerun. `benchmarks/physics.py` is planned (issue 35):
listed before it lands, so it may be absent.
"""

from __future__ import annotations

import json
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


#: Runs each script given as `__main__` with `--help` (its folder first on `sys.path`, as for
#: `python script.py`) in this one process, where the scripts' heavy imports (torch, MuJoCo) load
#: once, and prints as JSON each script's exit code, whether it printed a usage line, and the
#: tail of what it printed.
HELP_PROBE = """
import contextlib, io, json, os, runpy, sys
results = {}
for path in sys.argv[1:]:
    out = io.StringIO()
    sys.argv = [path, "--help"]
    sys.path.insert(0, os.path.dirname(path))
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        try:
            runpy.run_path(path, run_name="__main__")
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException as exc:
            code = repr(exc)
    sys.path.pop(0)
    text = out.getvalue()
    results[path] = [code, "usage:" in text, text[-500:]]
print(json.dumps(results))
"""


def test_every_named_benchmark_exists_and_answers_help():
    names = sorted(docs_names())
    missing = [n for n in names if not (BENCH / f"{n}.py").exists() and n not in PLANNED]
    assert not missing, f"docs name benchmarks that do not exist: {missing}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    scripts = {n: str(BENCH / f"{n}.py") for n in names if (BENCH / f"{n}.py").exists()}
    assert scripts
    proc = subprocess.run([sys.executable, "-c", HELP_PROBE, *scripts.values()], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    assert sorted(results) == sorted(scripts.values())
    failed = {name: results[path] for name, path in scripts.items()
              if results[path][0] != 0 or not results[path][1]}
    assert not failed, f"`--help` failed: {failed}"
