"""`dynslam synth PRESET --out DIR`: render a synthetic dynamic RGB-D scene with ground truth."""

from __future__ import annotations

import re
from pathlib import Path
from typing import List, Optional

import typer

from dynslam_cli.commands import _common as c


def parse_size(text: str) -> tuple[int, int]:
    from dynslam_cli.errors import DynslamError

    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text or "")
    if not m:
        raise DynslamError(f"--size '{text}' must look like WIDTHxHEIGHT, e.g. 640x480")
    return int(m.group(1)), int(m.group(2))


def register(app: typer.Typer) -> None:
    @app.command("synth")
    def synth(
        preset: str = typer.Argument(..., help="Scene preset: static, walker, crowd, kidnap, balloon, tracking."),
        out: Path = typer.Option(..., "--out", help="Output folder (created; an earlier scene there is replaced)."),
        frames: Optional[int] = typer.Option(None, "--frames", help="Number of frames (default synth.frames)."),
        seed: Optional[int] = typer.Option(None, "--seed", help="Random seed (default synth.seed)."),
        size: Optional[str] = typer.Option(None, "--size", help="Image size WIDTHxHEIGHT (default synth.width x synth.height)."),
        config: Optional[Path] = c.ConfigOpt,
        sets: Optional[List[str]] = c.SetOpt,
        quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    ) -> None:
        """Render a synthetic dynamic scene (RGB-D, poses, instance ids, motion masks, static mesh)."""
        from dynslam_cli.errors import DynslamError
        from dynslam_cli.synth.scene import PRESETS

        if preset not in PRESETS:
            raise DynslamError(f"unknown synthetic preset '{preset}'; presets: {', '.join(PRESETS)}")
        extra = [] if seed is None else [f"synth.seed={seed}"]
        if size is not None:  # checked with the config's rules, like --set synth.width=...
            width, height = parse_size(size)
            extra += [f"synth.width={width}", f"synth.height={height}"]
        cfg = c.resolve_config(f"synth/{preset}", config, list(sets or []) + extra).synth
        if frames is not None and frames < 1:
            raise DynslamError(f"--frames must be >= 1, got {frames}")

        from dynslam_cli.synth.render import render_preset

        res = render_preset(preset, out, cfg, frames=frames, progress=not quiet)
        per = res.seconds / max(res.frames, 1)
        typer.echo(f"synth {res.preset}: {res.frames} frames {res.width}x{res.height}, seed {cfg.seed}, "
                   f"{res.n_instances} instances, {res.seconds:.1f} s ({per:.3f} s/frame) -> {res.out_dir}")
