"""`dynslam view`: a Rerun recording of run folders (see dynslam_cli/view/)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("view")
    def view(
        run_dirs: List[Path] = typer.Argument(..., metavar="RUN_DIR",
                                              help="Run folder(s) holding traj_est.txt; several go into one recording."),
        out: Optional[Path] = typer.Option(
            None, "--out", help="Recording file (.rrd); default RUN_DIR/recording.rrd, or the runs' common folder."),
        every: Optional[int] = typer.Option(
            None, "--every", help="Images of every N-th frame (default: at most 100 frames with images per run)."),
        spawn: bool = typer.Option(False, "--spawn", help="Also open the Rerun viewer when one can be opened here."),
    ) -> None:
        """3-D view of runs: trajectories (estimate, aligned ground truth), camera frusta, RGB, depth,
        motion masks, rendered depth, mesh and classifier updates on a timeline, as a Rerun recording."""
        from dynslam_cli.view.recording import write_recording

        res = write_recording(run_dirs, out=out, every=every, spawn=spawn)
        for v in res.runs:
            gt = (f"ground truth {v.groundtruth_poses} poses ({v.alignment}, ATE RMSE {v.ate_rmse_m:.4f} m)"
                  if v.groundtruth_poses else "no ground truth")
            typer.echo(f"{v.prefix}: {v.frames} frames, images of {v.image_frames} (every {v.every}), {gt}, "
                       f"{v.masks} masks, {v.renders} rendered depths, {v.updates} classifier updates, "
                       f"mesh {v.mesh_vertices} vertices")
            for note in v.notes:
                typer.echo(f"  note: {note}")
        for note in res.notes:
            typer.echo(f"note: {note}")
        typer.echo(f"recording {res.out} ({res.size_bytes / 1e6:.1f} MB)"
                   + ("; streamed to the viewer" if res.spawned else "") + f"; open it with: rerun {res.out}")
