"""`embody report`: Tables I–III, figures and index.html of a run, from the artifact store."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path
from typing import Any

import click

from embody.cli.common import emit_json, json_option
from embody.errors import InputError


def ablation_configs(base: Any) -> dict[str, Any]:
    """The three Table II configs: the run's config with λ_close / λ_smooth switched off or on
    (on = the run's value, or the default when the run had it off)."""
    from embody.config import Config
    from embody.config.collision import CollisionConfig
    from embody.report.assemble import ABLATION_SETTINGS

    defaults, own = CollisionConfig(), base.collision
    out = {}
    for setting, (close, smooth) in ABLATION_SETTINGS.items():
        data = base.model_dump(mode="json")
        data["collision"].update(
            lambda_close=(own.lambda_close or defaults.lambda_close) if close else 0.0,
            lambda_smooth=(own.lambda_smooth or defaults.lambda_smooth) if smooth else 0.0)
        out[setting] = Config.model_validate(data)
    return out


def ablation_store(store_root: str | Path) -> Path:
    """Table II's own store (`<store>/ablation`): every setting is computed there by the same
    flow, so its times are measured the same way (a cache hit on the main run's collision
    results would carry timings taken under the full pipeline's load)."""
    from embody.store import ArtifactStore

    return ArtifactStore(store_root).work_dir / "ablation"  # local: the store's own folder


def run_ablation(store_root: str, run: str, say: Any = None) -> dict[str, Any]:
    """Run the Table II settings through the dataset flow (source + collide only) in the
    ablation store, cached there across reports → {setting: collision metrics}."""
    from embody.report.reader import COLLIDE, metrics_frame, open_run, run_config
    from embody.flows.env import configure

    say = say or (lambda text: None)
    store, manifest = open_run(store_root, run)
    configure(store.work_dir)
    dataset, split = manifest.data.get("dataset"), manifest.data.get("split")
    if not dataset:
        raise InputError(manifest.path, "dataset", "the run does not record its dataset")
    say("starting Prefect (a local server: ~3 s) for the Table II settings")
    from embody.flows.dataset import run_flow
    from embody.tasks.pipeline import Pipeline
    from embody.tasks.stages import COLLIDE as COLLIDE_STEP, SOURCE

    target = ablation_store(store.root)
    settings = ablation_configs(run_config(manifest))
    out = {}
    for k, (setting, cfg) in enumerate(settings.items(), 1):
        slug = re.sub(r"[^a-z]+", "-", setting.lower()).strip("-")
        cfg = cfg.model_copy(update={"run": cfg.run.model_copy(
            update={"name": f"{run}.ablation-{slug}", "store": str(target)})})
        say(f"Table II setting {k}/{len(settings)}: {setting}")
        t0 = time.perf_counter()
        summary = run_flow(dataset, cfg, split=split, progress=True,
                           pipeline=Pipeline(SOURCE, (COLLIDE_STEP,)))
        computed = summary["computed"].get(COLLIDE, 0)
        say(f"  {setting}: {computed} computed, {summary['ok'] - computed} cached "
            f"({time.perf_counter() - t0:.1f} s)")
        _, ablated = open_run(target, cfg.run.name)
        out[setting] = metrics_frame(ablated, COLLIDE)
    return out


@click.command("report")
@click.argument("run", required=False)
@click.option("--store", "store_root", default="embody-store", show_default=True,
              type=click.Path(file_okay=False),
              help="Artifact store: a directory, or s3://bucket/prefix (gs://, az://).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False),
              help="Output folder [default: reports/<run>].")
@click.option("--ablation", is_flag=True,
              help="Also run the three Table II collision settings (cached like any run).")
@click.option("--max-figures", type=click.IntRange(min=0), default=24, show_default=True,
              help="Wrist and location-error plots, for the sequences with the largest IK "
                   "error (comparison sheets and previews: every rendered sequence).")
@click.option("--max-sheets", type=click.IntRange(min=0), default=4, hidden=True,
              help="Ignored: the report shows the sheets the render step stored, never renders.")
@json_option
def command(run: str | None, store_root: str, out_dir: str | None, ablation: bool,
            max_figures: int, max_sheets: int, as_json: bool) -> int:
    """Write the report of RUN (default: the store's latest main run) to reports/RUN/."""
    from embody.report import collect, default_out_dir, latest_run, write_report
    from embody.store import check_run_name

    def say(text: str) -> None:
        click.echo(f"embody report: {text}", err=True)

    run = check_run_name(run or latest_run(store_root), "RUN")
    say(f"reading run {run} (figures for up to {max_figures} sequences)")
    data = collect(store_root, run, max_figures=max_figures, max_sheets=max_sheets)
    if ablation:
        data.ablation = run_ablation(store_root, run, say)
    say("writing tables, figures and index.html")
    from embody.report.reader import open_run
    from embody.report.stamp import SOURCE_STAMP, source_digest, stamp_report

    target = Path(out_dir) if out_dir else default_out_dir(run)
    (target / SOURCE_STAMP).unlink(missing_ok=True)
    paths = write_report(data, target)
    stamp_report(paths.out_dir, source_digest(text=open_run(store_root, run)[0]
                                              .read_manifest_text(run)))
    summary = json.loads(paths.summary.read_text())
    if as_json:
        emit_json({"run": run, "out_dir": str(paths.out_dir), "index": str(paths.index),
                   "tables": {k: {e: str(p) for e, p in v.items()}
                              for k, v in paths.tables.items()},
                   "figures": [str(p) for p in paths.figures], "summary": summary})
    else:
        for name, files in paths.tables.items():
            click.echo(f"{name}: {files['md']}")
        click.echo(f"report: {paths.index}")
    return 0
