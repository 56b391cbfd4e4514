"""Figures written from result files: the ATE top view (ate.png), the classifier-update curves and the
input / rendered depth / motion mask montage (``dynslam plot``)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs
from dynslam_cli.utils.io import atomic_path

if TYPE_CHECKING:
    from dynslam_cli.eval.ate import AteResult
    from dynslam_cli.eval.tables import RunRecord


def plot_ate(result: AteResult, out_png: str | Path, title: str = "") -> Path:
    """Top view (the two axes of largest ground-truth extent): GT line, estimate coloured by error."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    gt, est, err = result.gt_xyz, result.est_xyz, result.errors
    axes = np.argsort(-np.ptp(gt, axis=0))[:2]
    axes.sort()
    names = "xyz"
    fig, ax = plt.subplots(figsize=(6, 5), dpi=100)
    ax.plot(gt[:, axes[0]], gt[:, axes[1]], "k--", lw=1, label="ground truth")
    pts = est[:, axes].reshape(-1, 1, 2)
    if len(pts) > 1:
        segs = np.concatenate([pts[:-1], pts[1:]], axis=1)
        lc = LineCollection(segs, cmap="viridis", linewidths=2)
        lc.set_array(err[:-1])
        ax.add_collection(lc)
        fig.colorbar(lc, ax=ax, label="position error (m)")
    ax.scatter(est[:1, axes[0]], est[:1, axes[1]], c="r", s=20, label="estimate start")
    ax.set_xlabel(f"{names[axes[0]]} (m)")
    ax.set_ylabel(f"{names[axes[1]]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale()
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title or f"ATE RMSE {result.rmse_m:.4f} m ({result.alignment}, still {result.rmse_still_m:.3f} m)",
                 fontsize=9)
    fig.tight_layout()
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    return Path(out_png)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_updates(recs: list[RunRecord], out: Path) -> list[Path]:
    paths = []
    sel = [r for r in recs if r.mode == "dynamic" and r.updates is not None]
    for s, rs in sorted(runs.group_by(sel, lambda r: r.seq).items()):
        plt = _plt()
        fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
        for r in sorted(rs, key=lambda r: (not r.replay, r.seed)):
            x = sorted(r.updates)
            ax.step([0, *x], range(len(x) + 1), where="post", color="C0" if r.replay else "C3", alpha=0.8,
                    label=f"{'with' if r.replay else 'without'} replay, seed {r.seed}")
        ax.set_xlabel("frame (or timestamp) of the update")
        ax.set_ylabel("classifier updates so far")
        ax.set_title(f"{s}: classifier updates", fontsize=9)
        ax.legend(fontsize=7)
        fig.tight_layout()
        p = out / "plots" / f"classifier_updates_{re.sub(r'[^A-Za-z0-9._-]+', '-', s)}.png"
        with atomic_path(p) as tmp:
            fig.savefig(tmp)
        plt.close(fig)
        paths.append(p)
    return paths


def _imread(path: Path, flags: int):
    """cv2.imread without its warning for files a run did not write (None then)."""
    import cv2

    return cv2.imread(str(path), flags) if path.is_file() else None


def montage(run_dir: Path, out_png: Path, frames: Optional[list[str]] = None, n: int = 4) -> Optional[Path]:
    """Rows of input RGB / rendered depth / motion mask at chosen mask timestamps (None when no masks)."""
    import cv2

    mdir = run_dir / "masks"
    stems = sorted((p.stem for p in mdir.glob("*.png")), key=lambda s: float(s) if _isfloat(s) else 0.0) \
        if mdir.is_dir() else []
    if not stems:
        return None
    if frames:
        missing = [f for f in frames if f not in stems]
        if missing:
            raise DynslamError(f"no mask for frame(s) {', '.join(missing)} in {mdir}")
        chosen = frames
    else:
        chosen = [stems[i] for i in np.unique(np.linspace(0, len(stems) - 1, min(n, len(stems))).astype(int))]
    sp = runs.sequence_path(run_dir)
    plt = _plt()
    fig, axes = plt.subplots(len(chosen), 3, figsize=(9, 2.4 * len(chosen)), dpi=90, squeeze=False)
    for row, ts in zip(axes, chosen, strict=False):
        rgb_p = sp / "rgb" / f"{ts}.png" if sp is not None else None
        panels = [
            ("input", cv2.imread(str(rgb_p))[..., ::-1] if rgb_p is not None and rgb_p.is_file() else None, None),
            ("rendered depth", _imread(run_dir / "renders" / f"{ts}_depth.png", cv2.IMREAD_UNCHANGED), "viridis"),
            ("motion mask", _imread(mdir / f"{ts}.png", cv2.IMREAD_GRAYSCALE), "gray"),
        ]
        for ax, (title, img, cmap) in zip(row, panels, strict=False):
            ax.axis("off")
            ax.set_title(f"{title} {ts}", fontsize=7)
            if img is None:
                ax.text(0.5, 0.5, "not saved", ha="center", va="center", fontsize=8)
            else:
                ax.imshow(img, cmap=cmap)
    fig.tight_layout()
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp)
    plt.close(fig)
    return out_png


def _isfloat(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False
