"""index.html opened in headless Chromium: it loads, shows the tables, and no image is broken."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from embody.report import figures
from embody.report.html import render_index
from embody.report.tables import Table

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: Skips without Chromium on a developer machine; fails under CI=true (see conftest.require_tool).
needs_chromium = pytest.mark.usefixtures("chromium")

_CHECK = """<script>window.addEventListener('load', () => {
  const imgs = [...document.images];
  document.body.setAttribute('data-images', imgs.length);
  document.body.setAttribute('data-broken',
    imgs.filter(i => !i.complete || i.naturalWidth === 0).map(i => i.getAttribute('src')).join('|'));
  document.body.setAttribute('data-tables',
    [...document.querySelectorAll('table.report')].map(t => t.id).join('|'));
});</script>"""


def browse(index: Path, tmp: Path) -> dict[str, str]:
    """Load `index` (a copy with a checker script, same folder so relative links resolve)."""
    probe = index.with_name("_probe.html")
    probe.write_text(index.read_text().replace("</body>", _CHECK + "</body>"))
    try:
        proc = subprocess.run(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
             "--no-first-run", "--disable-background-networking", "--disable-component-update",
             "--disable-sync", f"--user-data-dir={tmp / 'chromium-profile'}",
             "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()],
            capture_output=True, text=True, timeout=120)
    finally:
        probe.unlink()
    assert proc.returncode == 0, proc.stderr[-2000:]
    body = re.search(r"<body([^>]*)>", proc.stdout)
    assert body, proc.stdout[:2000]
    return dict(re.findall(r'data-([a-z]+)="([^"]*)"', body.group(1)))


def check_report_page(index: Path, tmp: Path, tables: set[str]) -> dict[str, str]:
    """Shared by the end-to-end report test: the page loads, has `tables`, no broken image."""
    attrs = browse(index, tmp)
    assert tables <= set(attrs["tables"].split("|")), attrs
    assert attrs["broken"] == "", f"broken images: {attrs['broken']}"
    return attrs


@needs_chromium
def test_index_in_chromium(tmp_path) -> None:
    out = tmp_path / "reports" / "demo"
    frame = pd.DataFrame({"Metric": ["a"], "Value": [1.0]})
    tables = {}
    for name in ("table1_collision", "table2_ablation", "table3_retargeting"):
        t = Table(name, name, frame)
        tables[name] = (t, t.write(out))
    coll = pd.DataFrame({"energy_before": [2.0, 1.0], "energy_after": [0.5, 0.0],
                         "reduction_pct": [75.0, 100.0], "pose_mse": [1e-4, 2e-4]},
                        index=["s0", "s1"])
    t = np.linspace(0, 2, 60)
    ref = np.stack([np.sin(t), np.cos(t), t], -1)[:, None, :].repeat(2, 1)
    figs = {"Collision": [figures.collision_energy(coll, out / "figures" / "energy.png")],
            "Wrists": [figures.wrist_tracks({"reference": ref, "IK only": ref + 0.01}, 30.0,
                                            out / "figures" / "wrists" / "s0.png", title="s0")]}
    index = render_index(out, run="demo", tables=tables, figures=figs, summary={"x": 1.5},
                         files=[], failures=[("s2", "boom")])
    attrs = check_report_page(index, tmp_path, {"table1_collision", "table2_ablation",
                                               "table3_retargeting"})
    assert attrs["images"] == "2"
    assert 'src="/' not in index.read_text() and "file:" not in index.read_text()
    # A missing figure must be caught.
    (out / "figures" / "energy.png").unlink()
    assert browse(index, tmp_path)["broken"] == "figures/energy.png"


def test_worst_window() -> None:
    err = np.zeros(100)
    err[40:50] = 1.0
    assert figures.worst_window(err, 10) == slice(40, 50)
    assert figures.worst_window(err[:5], 10) == slice(0, 5)
