"""`embody collide IN OUT`: reduce one motion's self-collision and write the fixed motion."""

from __future__ import annotations

import click

from embody.cli.common import (build_config, config_options, emit_json, input_options, input_sets,
                               json_option, load_input)
from embody.config.collision import MaskPreset


@click.command("collide")
@click.argument("src", metavar="IN", type=click.Path())
@click.argument("dst", metavar="OUT", type=click.Path())
@click.option("--preset", type=click.Choice(list(MaskPreset.__args__)), default=None,
              help="Joint mask preset (overrides collision.mask).")
@input_options
@config_options
@json_option
def command(src: str, dst: str, preset: str | None, fps: float | None, up_axis: str | None,
            hands: str | None, config_files: tuple[str, ...], sets: tuple[str, ...],
            as_json: bool) -> int:
    """Optimise the masked joints of IN against the self-collision energy; write OUT (npz)."""
    from embody.body import load_body_model
    from embody.collision.windows import mitigate_windowed as mitigate
    from embody.io import save

    extra = (f"collision.mask={preset}",) if preset else ()
    cfg = build_config(config_files, sets + extra + input_sets(fps, up_axis, hands))
    motion = load_input(src, cfg)
    result = mitigate(motion, load_body_model(cfg.body), cfg.collision)
    fixed = result.motion
    fixed.meta["collision"] = {k: v for k, v in result.metrics.items()}
    save(fixed, dst)
    m = result.metrics
    if as_json:
        emit_json({"in": src, "out": dst, **m})
    else:
        status = "no collision" if m["no_collision"] else f"-{m['reduction_pct']:.1f}%"
        click.echo(f"{src}: L_col {m['energy_before']:.6g} -> {m['energy_after']:.6g} ({status}), "
                   f"{m['steps']} steps, {m['runtime_s']:.2f} s -> {dst}")
    return 0
