"""`embody synth OUT`: write a synthetic signing dataset with recorded artifacts."""

from __future__ import annotations

import click

from embody.verdicts import plural

from embody.cli.common import emit_json, json_option


@click.command("synth")
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--n", "n", type=click.IntRange(min=1), default=24, show_default=True,
              help="Number of sequences.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed: same seed, same bytes.")
@json_option
def command(out: str, n: int, seed: int, as_json: bool) -> int:
    """Generate N sign-like SMPL-X sequences (90-180 frames, 30 fps) into OUT."""
    from embody.io import load
    from embody.synth import generate_dataset

    paths = generate_dataset(out, n=n, seed=seed)
    rows = []
    for path in paths:
        meta = load(path).meta
        rows.append({"path": str(path), "text": meta["text"],
                     "artifacts": [a["kind"] for a in meta["artifacts"]]})
    if as_json:
        emit_json({"out": out, "n": n, "seed": seed, "sequences": rows})
        return 0
    for row in rows:
        click.echo(f"{row['path']}  {row['text']}  [{', '.join(row['artifacts']) or 'clean'}]")
    click.echo(f"wrote {plural(len(paths), 'sequence')} to {out}")
    return 0
