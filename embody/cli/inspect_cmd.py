"""`embody inspect PATH`: what a motion file holds, after conversion to embody's conventions."""

from __future__ import annotations

import click

from embody.cli.common import emit_json, json_option


def _artifact_line(art: dict) -> str:
    extra = ", ".join(f"{k}={v}" for k, v in art.items() if k not in ("kind", "start", "end"))
    return f"{art.get('kind')} [{art.get('start')}, {art.get('end')})" + (f" {extra}" if extra else "")


@click.command("inspect")
@click.argument("path", type=click.Path())
@json_option
def command(path: str, as_json: bool) -> int:
    """Print format, frames, fps, hand convention, joint ranges, text and artifacts of PATH."""
    from embody.io import load
    from embody.io.summary import summarize

    info = summarize(load(path))
    if as_json:
        emit_json(info)
        return 0
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
    return 0
