"""index.html opened in headless Chromium at 1280 px: it loads, shows the tables, no image is
broken, every figure is shown at its natural size or links to itself, every sequence row links
to files that exist (images among them decode), and no text overflows its box."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pandas as pd
import pytest

from embody.report import figures
from embody.report.html import render_index
from embody.report.tables import Table

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: Skips without Chromium on a developer machine; fails under CI=true (see conftest.require_tool).
needs_chromium = pytest.mark.usefixtures("chromium")
WIDTH = 1280

_CHECK = """<script>window.addEventListener('load', async () => {
  const b = document.body, W = window.innerWidth;
  const imgs = [...document.images];
  b.setAttribute('data-images', imgs.length);
  b.setAttribute('data-broken',
    imgs.filter(i => !i.complete || i.naturalWidth === 0).map(i => i.getAttribute('src')).join('|'));
  b.setAttribute('data-tables',
    [...document.querySelectorAll('table.report')].map(t => t.id).join('|'));
  // A figure is readable when shown at natural size, or when a click opens it (link to itself).
  b.setAttribute('data-scaled', imgs.filter(i => {
    const a = i.closest('a');
    const linked = a && a.getAttribute('href') === i.getAttribute('src');
    return !linked && Math.abs(i.getBoundingClientRect().width - i.naturalWidth) > 1;
  }).map(i => i.getAttribute('src')).join('|'));
  // Each sequence row's links; the image ones must decode.
  const rows = [...document.querySelectorAll('#sequences tbody tr')].map(r => ({
    id: r.cells[0].textContent.trim(),
    links: [...r.querySelectorAll('a')].map(a => a.getAttribute('href'))}));
  const load = src => new Promise(ok => { const im = new Image();
    im.onload = () => ok(im.naturalWidth > 0); im.onerror = () => ok(false); im.src = src; });
  for (const r of rows) {
    r.decoded = [];
    for (const h of r.links) if (/\\.(png|gif|webp)$/.test(h)) r.decoded.push([h, await load(h)]);
  }
  b.setAttribute('data-rows', encodeURIComponent(JSON.stringify(rows)));
  // No horizontal page scroll at this width, and no element's text spills out of its box.
  const spill = [...document.querySelectorAll('body *')].filter(e =>
    e.children.length === 0 && e.textContent.trim() && !['SCRIPT', 'STYLE'].includes(e.tagName)
    && e.scrollWidth > e.clientWidth + 1 && getComputedStyle(e).display !== 'inline');
  const wide = [...document.querySelectorAll('.scroll')].filter(e => e.scrollWidth > e.clientWidth + 1);
  b.setAttribute('data-overflow', [
    ...(document.documentElement.scrollWidth > W ? ['page:' + document.documentElement.scrollWidth] : []),
    ...spill.map(e => e.tagName + ':' + e.textContent.trim().slice(0, 40)),
    ...wide.map(e => 'table:' + (e.querySelector('table') || {}).id)].join('|'));
  b.setAttribute('data-done', '1');
});</script>"""


def browse(index: Path, tmp: Path) -> dict[str, str]:
    """Load `index` at 1280 px (a copy with a checker script, same folder so relative links
    resolve) and return the checker's findings."""
    probe = index.with_name("_probe.html")
    probe.write_text(index.read_text().replace("</body>", _CHECK + "</body>"))
    try:
        proc = subprocess.run(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
             "--no-first-run", "--disable-background-networking", "--disable-component-update",
             "--disable-sync", f"--user-data-dir={tmp / 'chromium-profile'}",
             f"--window-size={WIDTH},900", "--hide-scrollbars",
             "--virtual-time-budget=10000", "--dump-dom", probe.as_uri()],
            capture_output=True, text=True, timeout=120)
    finally:
        probe.unlink()
    assert proc.returncode == 0, proc.stderr[-2000:]
    body = re.search(r"<body([^>]*)>", proc.stdout)
    assert body, proc.stdout[:2000]
    attrs = dict(re.findall(r'data-([a-z]+)="([^"]*)"', body.group(1)))
    assert attrs.get("done") == "1", "the checker did not finish"
    return attrs


def check_report_page(index: Path, tmp: Path, tables: set[str]) -> dict[str, str]:
    """Shared with the end-to-end report test: the page loads with `tables`, no broken image,
    figures readable, sequence links working, nothing overflowing at 1280 px."""
    attrs = browse(index, tmp)
    assert tables <= set(attrs["tables"].split("|")), attrs
    assert attrs["broken"] == "", f"broken images: {attrs['broken']}"
    assert attrs["scaled"] == "", f"scaled-down figures without a link: {attrs['scaled']}"
    assert attrs["overflow"] == "", f"overflows at {WIDTH} px: {attrs['overflow']}"
    rows = json.loads(unquote(attrs["rows"]))
    for row in rows:
        for href in row["links"]:
            assert (index.parent / unquote(href)).is_file(), (row["id"], href)
        assert all(ok for _, ok in row["decoded"]), row
    attrs["rows"] = rows  # type: ignore[assignment]
    return attrs


#: `embody.metrics.fidelity.LOCATION_LANDMARKS` order (the stored indices point into it).
NAMES = ["head_top", "forehead", "left_eye", "right_eye", "nose", "mouth", "chin", "left_cheek",
         "right_cheek", "throat", "left_shoulder", "right_shoulder", "sternum", "belly",
         "left_hip", "right_hip"]


def test_location_plot_labels_landmarks(tmp_path) -> None:
    """The location-error figure names the landmarks the hand was nearest, and only those."""
    import matplotlib.pyplot as plt
    t = np.arange(90)
    err = np.stack([0.1 + 0.05 * np.sin(t / 9), np.full(90, 0.3)], 1)
    landmark = np.stack([np.where(t < 45, 6, 12), np.full(90, 13)], 1)  # chin → sternum; belly
    seen: list[str] = []
    real_text = plt.Axes.text

    def spy(self, x, y, s, *a, **k):
        seen.append(str(s))
        return real_text(self, x, y, s, *a, **k)

    plt.Axes.text = spy
    try:
        path = figures.location_error(err, landmark, NAMES, 30.0, tmp_path / "loc.png", title="s")
    finally:
        plt.Axes.text = real_text
    assert sorted(set(seen)) == ["belly", "chin", "sternum"]
    from PIL import Image
    with Image.open(path) as im:
        assert im.size[0] >= 1000  # natural size is readable


def _png(path: Path, width: int, height: int) -> bytes:
    import matplotlib.pyplot as plt
    fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    fig.text(0.1, 0.5, path.stem)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path.read_bytes()


@needs_chromium
def test_report_page_in_chromium(tmp_path) -> None:
    from embody.report import RunData, write_report

    ids = [f"sign_{k:02d}_with_a_rather_long_identifier" for k in range(5)] + ["failed one"]
    ok = ids[:5]
    t = np.linspace(0, 2, 60)
    ref = np.stack([np.sin(t), np.cos(t), t], -1)[:, None, :].repeat(2, 1)
    sequences = pd.DataFrame(
        {"status": ["ok"] * 5 + ["failed"], "error": [""] * 5 + ["collide: boom"],
         "text": ["a fairly long gloss text that has to wrap inside its cell " * 2] * 6},
        index=pd.Index(ids, name="id"))
    from embody.collision.metrics import sequence_metrics
    rng = np.random.default_rng(0)
    coll = pd.DataFrame.from_dict(
        {sid: sequence_metrics(x0 := rng.normal(size=(12, 55, 3)), x0 + 0.01,
                               energy_before=1.0 + k, energy_after=0.1, runtime_s=1.0, steps=5)
         for k, sid in enumerate(ok)}, orient="index")
    retarget = pd.DataFrame({"wrist_pos_err_mm": np.linspace(5, 25, 5),
                             "wrist_rot_err_deg": np.ones(5),
                             "joint_limit_violations": np.zeros(5),
                             "velocity_violations": np.zeros(5),
                             "self_collision_frames": [0, 0, 3, 0, 0]}, index=ok)
    data = RunData("demo", sequences, collision=coll, retarget=retarget)
    data.other["metrics"] = retarget.iloc[:, 2:].copy()
    sheet = _png(tmp_path / "sheet.png", 2400, 600)  # wider than the page: shown scaled, linked
    gif = _png(tmp_path / "preview.png", 64, 48)
    for sid in ok:
        data.sheets[sid] = sheet
        data.previews[sid] = (gif, ".png")
        data.wrists[sid] = {"reference": ref, "IK only": ref + 0.01}
        data.wrist_fps[sid] = 30.0
        landmark = np.repeat([[6, 12], [12, 12]], 30, axis=0)  # chin then sternum (left hand)
        data.locations[sid] = {"err": np.abs(ref[:, :, 0]) * 0.2, "landmark": landmark,
                               "names": NAMES, "fps": 30.0}
    paths = write_report(data, tmp_path / "reports" / "demo")
    attrs = check_report_page(paths.index, tmp_path, {"verdicts", "table1_collision",
                                                     "table3_retargeting", "sequences"})
    rows = {r["id"]: r["links"] for r in attrs["rows"]}  # type: ignore[index]
    assert set(rows) == set(ids)
    for sid in ok:  # sheet, preview, wrist and location plot of every finished sequence
        assert len(rows[sid]) == 4, rows[sid]
        assert f"figures/location/{sid}.png" in rows[sid]
    assert rows["failed one"] == []
    html = paths.index.read_text()
    assert 'src="/' not in html and "file:" not in html
    # The checks can fail: a missing figure, and a figure shrunk without a link.
    (paths.out_dir / "figures" / "collision_energy.png").unlink()
    assert browse(paths.index, tmp_path)["broken"] == "figures/collision_energy.png"
    html = html.replace('<a href="figures/pose_vs_reduction.png" title="open at full size">',
                        "<a>")
    paths.index.write_text(html.replace('<img src="figures/pose_vs_reduction.png"',
                                        '<img style="width:100px" src="figures/pose_vs_reduction.png"'))
    assert browse(paths.index, tmp_path)["scaled"] == "figures/pose_vs_reduction.png"


@needs_chromium
def test_overflow_is_caught(tmp_path) -> None:
    out = tmp_path / "r"
    out.mkdir()
    frame = pd.DataFrame({"Metric": ["a"], "Value": [1.0]})
    t = Table("t", "t", frame)
    index = render_index(out, run="x" * 400, tables={"t": (t, t.write(out))}, figures={},
                         summary={"x": 1.5}, files=[], failures=[])
    index.write_text(index.read_text().replace("overflow-wrap:anywhere", "white-space:nowrap"))
    assert browse(index, tmp_path)["overflow"]


def test_worst_window() -> None:
    err = np.zeros(100)
    err[40:50] = 1.0
    assert figures.worst_window(err, 10) == slice(40, 50)
    assert figures.worst_window(err[:5], 10) == slice(0, 5)
