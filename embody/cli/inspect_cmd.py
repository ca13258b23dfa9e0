"""`embody inspect PATH`: what a motion file (or dataset) holds, after conversion to embody's
conventions."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from embody.verdicts import plural

from embody.cli.common import emit_json, json_option


def _artifact_line(art: dict) -> str:
    extra = ", ".join(f"{k}={v}" for k, v in art.items() if k not in ("kind", "start", "end"))
    return f"{art.get('kind')} [{art.get('start')}, {art.get('end')})" + (f" {extra}" if extra else "")


def _is_dataset(path: Path) -> bool:
    from embody.io.soke import is_sequence_dir

    return path.suffix.lower() == ".csv" or (path.is_dir() and any(path.iterdir())
                                               and not is_sequence_dir(path))


def _dataset_info(path: Path, split: str | None) -> dict[str, Any]:
    from embody.io import load_dataset

    ds = load_dataset(path, split)
    return {"dataset": str(path), "kind": ds.kind, "sequences": len(ds), "ids": ds.ids}


def _echo_motion(info: dict[str, Any]) -> None:
    click.echo(f"{info['path']}")
    click.echo(f"  format           {info['format']}")
    click.echo(f"  frames           {info['frames']} @ {info['fps']:g} fps ({info['duration_s']:.2f} s)")
    converted = ", converted to absolute" if info["hand_convention"] == "relative" else ""
    click.echo(f"  hand convention  {info['hand_convention']} in source{converted}")
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
@click.option("--fps", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Frame rate of formats that store none (SOKE, SignAvatars, arrays). [30]")
@click.option("--split", type=click.Choice(["train", "val", "test"]), default=None,
              help="Split of a SOKE root (datasets only).")
@json_option
def command(path: str, fps: float | None, split: str | None, as_json: bool) -> int:
    """Print format, frames, fps, hand convention, joint ranges, text and artifacts of PATH.

    For a dataset (a folder of motion files, a SOKE root or a CSV manifest) list its sequences.
    """
    from embody.io import load
    from embody.io.summary import summarize

    target = Path(path)
    if split is not None or _is_dataset(target):
        info = _dataset_info(target, split)
        if as_json:
            emit_json(info)
        else:
            click.echo(f"{info['dataset']}: {info['kind']} dataset, {plural(info['sequences'], 'sequence')}")
            for seq_id in info["ids"]:
                click.echo(f"  {seq_id}")
        return 0
    info = summarize(load(target, fps=fps))
    if as_json:
        emit_json(info)
    else:
        _echo_motion(info)
    return 0
