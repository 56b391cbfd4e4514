"""`dynslam prior fit`: pre-train the prior motion classifier (people vs the rest)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from dynslam_cli.commands import _common as c


def register(app: typer.Typer) -> None:
    from dynslam_cli.cli import make_group

    group = make_group("The prior motion classifier (paper: incorporation of prior knowledge).")

    @group.command("fit")
    def fit(
        out: Path = typer.Option(..., "--out", help="Prior file to write (load it with --set motion.prior=FILE)."),
        images: Optional[Path] = typer.Option(None, "--images", help="Folder of photos; people found by --yolo are positives."),
        yolo: Optional[str] = typer.Option(None, "--yolo", help="YOLOv8-seg ONNX model (default motion.segmenter_model)."),
        synth: Optional[List[str]] = typer.Option(None, "--synth",
                                                  help="Synthetic preset or scene folder (repeatable); movers are positives."),
        frames: int = typer.Option(30, "--frames", help="Frames used (rendered) per synthetic scene."),
        stride: int = typer.Option(1, "--stride", help="Use every S-th synthetic frame."),
        steps: int = typer.Option(300, "--steps", help="Adam steps of the fit."),
        test_fraction: float = typer.Option(0.25, "--test-fraction", help="Held-out fraction for the accuracy report."),
        positive: str = typer.Option("person", "--positive", help="Comma-separated class names counted as dynamic (images)."),
        config: Optional[Path] = c.ConfigOpt,
        sets: Optional[List[str]] = c.SetOpt,
    ) -> None:
        """Train the prior classifier on labelled crops and report its held-out accuracy."""
        from dynslam_cli.motion.prior import fit_prior

        cfg = c.resolve_config(None, config, sets)
        r = fit_prior(out, cfg, images=images, yolo=yolo, synth=synth or [], frames=frames, stride=stride,
                      test_fraction=test_fraction, steps=steps,
                      positive=[p.strip() for p in positive.split(",") if p.strip()])
        typer.echo(f"prior ({r.encoder}): {r.samples} crops, {r.positives} positive; "
                   f"accuracy train {r.train_accuracy:.3f}, held-out {r.test_accuracy:.3f} on {r.test_samples} "
                   f"(precision {r.test_precision:.3f}, recall {r.test_recall:.3f}); {r.seconds:.1f} s")
        for src, s in r.sources.items():
            typer.echo(f"  {src}: {s['samples']} crops, {s['positives']} positive")
        typer.echo(f"wrote {r.out}")

    app.add_typer(group, name="prior")
