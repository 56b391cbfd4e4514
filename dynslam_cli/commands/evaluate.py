"""`dynslam eval-ate`, `eval-mesh`, `eval-masks`: evaluate run folders (see dynslam_cli/eval/).

Only completed runs (run.json status) are evaluated: a single folder that is not completed is an
error naming its status; of several folders, those not completed are skipped with a one-line
warning.  ``--include-incomplete`` evaluates them anyway (e.g. the trajectory of a failed run).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

IncludeOpt = typer.Option(False, "--include-incomplete",
                          help="Also evaluate runs whose run.json is not 'completed' (running, failed, interrupted, missing).")


def _runs_to_evaluate(run_dirs: List[Path], include_incomplete: bool) -> List[Path]:
    """One folder: itself (the evaluator refuses it when incomplete).  Several: the completed ones,
    with a warning on stderr for each skipped folder; none completed is an error."""
    from dynslam_cli.errors import DynslamError
    from dynslam_cli.eval import runs

    if len(run_dirs) == 1:
        return list(run_dirs)
    keep, warnings = runs.select_completed(run_dirs, include_incomplete)
    for w in warnings:
        typer.echo(f"warning: {w}", err=True)
    if not keep:
        raise DynslamError(f"none of the {len(run_dirs)} run folders is completed; pass --include-incomplete "
                           "to evaluate them anyway")
    return keep


def register(app: typer.Typer) -> None:
    @app.command("eval-ate")
    def eval_ate(
        run_dirs: List[Path] = typer.Argument(..., help="Run folder(s) holding traj_est.txt."),
        gt: Optional[Path] = typer.Option(None, "--gt", help="Ground-truth TUM file (default: run.json)."),
        align: Optional[str] = typer.Option(None, "--align", help="se3 (default, eval.align), sim3, origin or none."),
        max_diff: Optional[float] = typer.Option(None, "--max-diff", help="Max time difference (s), eval.max_time_diff."),
        plot: bool = typer.Option(True, "--plot/--no-plot", help="Write ate.png."),
        online: bool = typer.Option(False, "--online", help="Score traj_online.txt (each frame's pose when it was "
                                    "done) into ate_online.json / .png instead."),
        include_incomplete: bool = IncludeOpt,
    ) -> None:
        """ATE RMSE (evo APE on translations) of each run; writes ate.json and ate.png."""
        from dynslam_cli.eval.ate import evaluate_run_ate

        for d in _runs_to_evaluate(run_dirs, include_incomplete):
            r = evaluate_run_ate(d, gt=gt, align=align, max_diff=max_diff, plot=plot,
                                 include_incomplete=include_incomplete, online=online)
            what = "online ATE RMSE" if online else "ATE RMSE"
            typer.echo(f"{d}: {what} {r.rmse_m:.4f} m ({r.alignment}, {r.matched}/{r.est_poses} poses matched; "
                       f"still camera {r.rmse_still_m:.4f} m)")

    @app.command("eval-mesh")
    def eval_mesh(
        run_dirs: List[Path] = typer.Argument(..., help="Run folder(s) holding mesh.ply and traj_est.txt."),
        ref: Optional[Path] = typer.Option(None, "--ref", help="Reference (synthetic: static_mesh.ply; Bonn: laser cloud)."),
        cull: bool = typer.Option(True, "--cull/--no-cull", help="Cull the reference to the camera frusta (completion)."),
        gt: Optional[Path] = typer.Option(None, "--gt", help="Ground truth placing the reference (default: run.json)."),
        include_incomplete: bool = IncludeOpt,
    ) -> None:
        """Mesh accuracy, completion and completion ratio; writes mesh_metrics.json."""
        from dynslam_cli.eval.mesh import evaluate_run_mesh

        for d in _runs_to_evaluate(run_dirs, include_incomplete):
            r = evaluate_run_mesh(d, ref=ref, cull=cull, gt=gt, include_incomplete=include_incomplete)
            typer.echo(f"{d}: accuracy {100 * r.accuracy_m:.2f} cm, completion {100 * r.completion_m:.2f} cm, "
                       f"completion ratio {100 * r.completion_ratio:.1f} % (< {100 * r.threshold_m:.0f} cm)")

    @app.command("eval-masks")
    def eval_masks(
        run_dirs: List[Path] = typer.Argument(..., help="Synthetic run folder(s) holding masks/<ts>.png."),
        gt_dir: Optional[Path] = typer.Option(None, "--gt-dir", help="Ground-truth masks (default: the scene's dynamic/)."),
        include_incomplete: bool = IncludeOpt,
    ) -> None:
        """Motion-mask IoU / precision / recall against the scene's dynamic masks; writes mask_metrics.json."""
        from dynslam_cli.eval.masks import evaluate_run_masks

        def f(v):
            return "—" if v is None else f"{v:.3f}"

        for d in _runs_to_evaluate(run_dirs, include_incomplete):
            r = evaluate_run_masks(d, gt_dir=gt_dir, include_incomplete=include_incomplete)
            typer.echo(f"{d}: {r.frames} frames ({r.frames_moving} with movers): IoU {f(r.mean_iou_moving)}, "
                       f"precision {f(r.mean_precision_moving)}, recall {f(r.mean_recall_moving)} (frames with movers); "
                       f"pooled IoU {f(r.pooled_iou)}")
