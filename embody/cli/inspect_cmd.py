"""`embody inspect PATH`: what a motion file (or dataset) holds, after conversion to embody's
conventions."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from embody.verdicts import plural

from embody.cli.common import (build_config, config_options, emit_json, input_options, input_sets,
                               json_option, load_input)


def _artifact_line(art: dict) -> str:
    extra = ", ".join(f"{k}={v}" for k, v in art.items() if k not in ("kind", "start", "end"))
    return f"{art.get('kind')} [{art.get('start')}, {art.get('end')})" + (f" {extra}" if extra else "")


def _is_dataset(path: Path) -> bool:
    from embody.io.soke import is_sequence_dir

    return path.suffix.lower() == ".csv" or (path.is_dir() and any(path.iterdir())
                                               and not is_sequence_dir(path))


def _dataset_info(path: Path, split: str | None, limits: Any = None) -> dict[str, Any]:
    from embody.io import load_dataset

    ds = load_dataset(path, split, limits)
    return {"dataset": str(path), "kind": ds.kind, "sequences": len(ds), "ids": ds.ids}


def _echo_motion(info: dict[str, Any]) -> None:
    click.echo(f"{info['path']}")
    click.echo(f"  format           {info['format']}")
    click.echo(f"  frames           {info['frames']} @ {info['fps']:g} fps ({info['duration_s']:.2f} s)")
    converted = ", converted to absolute" if info["hand_convention"] == "relative" else ""
    click.echo(f"  hand convention  {info['hand_convention']} in source{converted}")
    for name in ("fps", "up_axis", "hands"):
        item = info.get("provenance", {}).get(name)
        if item:
            label = {"fps": "fps from", "up_axis": "up axis", "hands": "hands from"}[name]
            value = f"{item['value']:g}" if isinstance(item["value"], float) else item["value"]
            click.echo(f"  {label:<16} {value}: {item['origin']}")
            judged = info.get("provenance", {}).get("check", {}).get(name)
            if judged:
                said = judged["data"] if judged["data"] is not None else "cannot tell"
                click.echo(f"  {'':<16} the data: {said} ({judged['detail']})")
    click.echo(f"  gender           {info['gender']}")
    click.echo("  joint ranges (angle, deg):")
    for name, r in info["joint_ranges"].items():
        click.echo(f"    {name:<11} {r['min_deg']:7.1f} .. {r['max_deg']:7.1f}")
    if "text" in info:
        click.echo(f"  text             {info['text']}")
    if "gloss" in info:
        click.echo(f"  gloss            {' '.join(map(str, info['gloss']))}")
    if "artifacts" in info:
        click.echo(f"  artifacts        {len(info['artifacts'])}")
        for art in info["artifacts"]:
            click.echo(f"    {_artifact_line(art)}")


@click.command("inspect")
@click.argument("path", type=click.Path())
@click.option("--split", type=click.Choice(["train", "val", "test"]), default=None,
              help="Split of a SOKE root (datasets only).")
@input_options
@config_options
@json_option
def command(path: str, split: str | None, fps: float | None, up_axis: str | None,
            hands: str | None, config_files: tuple[str, ...], sets: tuple[str, ...],
            as_json: bool) -> int:
    """Print format, frames, fps, hand convention, joint ranges, text and artifacts of PATH, and
    where the fps, up axis and hand convention came from (the file, a detected layout, the
    dataset's documented default, or an override).

    For a dataset (a folder of motion files, a SOKE root or a CSV manifest) list its sequences.
    """
    from embody.io.summary import summarize

    limits = build_config(config_files, sets).io
    target = Path(path)
    if split is not None or _is_dataset(target):
        info = _dataset_info(target, split, limits)
        if as_json:
            emit_json(info)
        else:
            click.echo(f"{info['dataset']}: {info['kind']} dataset, {plural(info['sequences'], 'sequence')}")
            for seq_id in info["ids"]:
                click.echo(f"  {seq_id}")
        return 0
    cfg = build_config(config_files, tuple(sets) + input_sets(fps, up_axis, hands))
    info = summarize(load_input(str(target), cfg))
    if as_json:
        emit_json(info)
    else:
        _echo_motion(info)
    from embody.io.conventions import layout_warnings

    for warning in layout_warnings(info.get("provenance", {})):
        click.echo(f"warning: {info['path']}: {warning}", err=True)
    return 0
