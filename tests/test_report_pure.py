"""The report is a pure reader of the store: it imports nothing that computes robotics."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import embody.report

#: Packages whose code recomputes what the pipeline stored (or needs a robot/body/GL context).
FORBIDDEN = ("embody.tasks", "embody.robot", "embody.body", "embody.render", "embody.retarget",
             "embody.critic", "embody.collision", "embody.flows", "tasks", "flows", "torch",
             "mujoco", "pytorch_kinematics")
REPORT = Path(embody.report.__file__).parent


def _imports(path: Path) -> list[tuple[int, str]]:
    """Every module an `import` / `from … import` names (inside functions too), and every
    string constant that names an embody module (lazy imports by name)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.append((node.lineno, node.module))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and node.value.startswith("embody.") and " " not in node.value:
            out.append((node.lineno, node.value))
    return out


def _bad(name: str) -> bool:
    return any(name == f or name.startswith(f + ".") for f in FORBIDDEN)


def test_report_imports_no_robotics() -> None:
    files = sorted(REPORT.glob("*.py"))
    assert len(files) >= 8
    bad = [f"{p.name}:{line} {name}" for p in files for line, name in _imports(p) if _bad(name)]
    assert bad == []


def test_the_check_catches_a_robotics_import(tmp_path) -> None:
    """The AST walk sees imports inside functions (a test that cannot fail is a defect)."""
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from embody.retarget.validation import validation_counts\n"
                     "    import embody.robot as r\n")
    assert [n for _, n in _imports(probe) if _bad(n)] == ["embody.retarget.validation", "embody.robot"]


def test_loading_every_report_module_loads_no_torch_or_mujoco() -> None:
    code = ("import sys, importlib, pkgutil, embody.report as r\n"
            "for m in pkgutil.iter_modules(r.__path__): importlib.import_module('embody.report.' + m.name)\n"
            "bad = [m for m in ('torch', 'mujoco', 'embody.tasks', 'embody.robot') if m in sys.modules]\n"
            "assert not bad, bad\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
