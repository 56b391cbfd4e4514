"""Figures written from result files: the ATE top view (ate.png), the classifier-update curves and the
input / rendered depth / motion mask montage (``dynslam plot``).

Every figure names what it shows: the sequence (run.json ``sequence.dataset``/``name``), the mode and
the frame range (run.json ``frames``, config.yaml ``data.start``/``data.stride``), see
:func:`run_caption`.  The montage finds a mask's input images through the sequence's own lists
(``rgb.txt``/``depth.txt`` or ``associations.txt``, read with the TUM reader's parsers), matching
timestamps numerically: a run names its masks after the timestamp as written in ``rgb.txt``
(``1548339824.902700``) while the image file may be named differently (``rgb/1548339824.90270.png``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval import runs
from dynslam_cli.utils.io import atomic_path

# plot_ate takes an eval/ate.py AteResult and plot_updates eval/tables.py RunRecords; neither is imported here,
# because both modules import this one (no import cycle, not even for type checking).

STAMP_TOL_S = 5e-4  # a mask's timestamp matches a listed image within this (frames are ≥ 10 ms apart)
RENDER_DEPTH_SCALE = 5000.0  # renders/<ts>_depth.png: uint16, metres × 5000 (run/loop.py)
DEPTH_CMAP = "viridis"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, out_png: str | Path) -> Path:
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp)
    _plt().close(fig)
    return Path(out_png)


# ---------------------------------------------------------------- what a run is
def _int_or(value, default: Optional[int]) -> Optional[int]:
    try:
        return int(value)
    except (TypeError, ValueError):
        return default


def frame_range(run_dir: Path) -> str:
    """``frames 0–298 step 2 (150 frames)``: the sequence positions the run processed ('' when unknown)."""
    meta = runs.read_run_json(run_dir)
    data = runs.read_run_config(run_dir).get("data") or {}
    data = data if isinstance(data, dict) else {}
    start = _int_or(data.get("start"), 0)
    stride = max(1, _int_or(data.get("stride"), 1))
    n = _int_or(meta.get("frames"), None)
    step = f" step {stride}" if stride > 1 else ""
    if n:
        return f"frames {start}–{start + stride * (n - 1)}{step} ({n} frames)"
    if data:
        return f"frames from {start}{step}"
    return ""


def run_caption(run_dir: Path) -> str:
    """One line naming a run: ``bonn/crowd_150_449_s2, dynamic, frames 0–298 step 2 (150 frames), seed 0``."""
    meta = runs.read_run_json(run_dir)
    seq = runs.sequence_info(run_dir, meta)
    name = "/".join(str(seq[k]) for k in ("dataset", "name") if seq.get(k)) or Path(run_dir).name
    mode, variant = meta.get("mode"), meta.get("variant")
    parts = [name, f"{mode}{f' ({variant})' if variant and variant != mode else ''}" if mode else "",
             frame_range(run_dir), f"seed {meta['seed']}" if meta.get("seed") is not None else ""]
    return ", ".join(p for p in parts if p)


# ---------------------------------------------------------------- ate.png
def plot_ate(result: Any, out_png: str | Path, title: str = "", run_dir: Optional[str | Path] = None) -> Path:
    """Top view (the two axes of largest ground-truth extent): GT line, estimate coloured by error.

    The title names the run (:func:`run_caption` of ``run_dir``; by default the folder of ``out_png``
    when it holds a run.json) above ``title`` or, without one, the ATE and still-camera numbers.
    """
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    plt = _plt()
    gt, est, err = result.gt_xyz, result.est_xyz, result.errors
    axes = np.argsort(-np.ptp(gt, axis=0))[:2]
    axes.sort()
    names = "xyz"
    fig, ax = plt.subplots(figsize=(6.4, 5.4), dpi=100, layout="constrained")
    ax.plot(gt[:, axes[0]], gt[:, axes[1]], "k--", lw=1, label="ground truth")
    pts = est[:, axes].reshape(-1, 1, 2)
    cmap = plt.get_cmap("viridis")
    if len(pts) > 1:
        segs = np.concatenate([pts[:-1], pts[1:]], axis=1)
        lc = LineCollection(segs, cmap=cmap, linewidths=2)
        lc.set_array(0.5 * (err[:-1] + err[1:]))
        ax.add_collection(lc)
        fig.colorbar(lc, ax=ax, label="position error (m)")
    handles, labels = ax.get_legend_handles_labels()
    handles.append(Line2D([], [], color=cmap(0.55), lw=2))
    labels.append(f"estimate ({result.alignment}-aligned, colour = error)")
    start = ax.scatter(est[:1, axes[0]], est[:1, axes[1]], c="r", s=20, zorder=3)
    handles.append(start)
    labels.append("estimate start")
    ax.set_xlabel(f"{names[axes[0]]} (m)")
    ax.set_ylabel(f"{names[axes[1]]} (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale()
    ax.legend(handles, labels, loc="best", fontsize=8)
    run_dir = Path(run_dir) if run_dir is not None else Path(out_png).parent
    try:
        caption = run_caption(run_dir) if (run_dir / "run.json").is_file() else ""
    except DynslamError:  # a corrupt run.json costs the plot its run line, not the ATE
        caption = ""
    stats = title or (f"ATE RMSE {result.rmse_m:.4f} m ({result.alignment}, {result.matched} poses), "
                      f"still camera {result.rmse_still_m:.3f} m")
    ax.set_title("\n".join(t for t in (caption, stats) if t), fontsize=9)
    return _save(fig, out_png)


# ---------------------------------------------------------------- classifier updates
def plot_updates(recs: list[Any], out: Path) -> list[Path]:
    """One figure per sequence: cumulative classifier updates over the frames, with and without replay."""
    paths = []
    sel = [r for r in recs if r.mode == "dynamic" and r.updates is not None]
    for s, rs in sorted(runs.group_by(sel, lambda r: r.seq).items()):
        plt = _plt()
        fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=100, layout="constrained")
        ranges = []
        for r in sorted(rs, key=lambda r: (not r.replay, r.seed)):
            x = sorted(r.updates)
            n = _int_or(runs.read_run_json(r.path).get("frames"), None)
            end = [n - 1] if n and (not x or x[-1] < n - 1) else []  # flat to the run's last frame
            ax.step([0, *x, *end], [*range(len(x) + 1), *([len(x)] if end else [])], where="post",
                    color="C0" if r.replay else "C3", alpha=0.8,
                    label=f"{'with' if r.replay else 'without'} replay, seed {r.seed} ({len(x)} updates)")
            fr = frame_range(r.path)
            if fr and fr not in ranges:
                ranges.append(fr)
        ax.set_xlabel("frame of the update (index in the run)")
        ax.set_ylabel("classifier updates so far")
        ax.set_title(f"{s}: classifier updates, dynamic mode\n{'; '.join(ranges) or 'frame range unknown'}",
                     fontsize=9)
        ax.legend(fontsize=7)
        p = out / "plots" / f"classifier_updates_{re.sub(r'[^A-Za-z0-9._-]+', '-', s)}.png"
        paths.append(_save(fig, p))
    return paths


# ---------------------------------------------------------------- montage
@dataclass
class _Listed:
    timestamp: float
    stamp: str
    rgb: Path
    depth: Optional[Path]
    index: Optional[int]  # position in the run's cut sequence (data.start/frames/stride)


def _sequence_inputs(sp: Path, data: dict) -> list[_Listed]:
    """The sequence's images by rgb timestamp, associated and cut as the reader does (data/tum.py)."""
    from dynslam_cli.data import tum

    assoc = sp / "associations.txt"
    if assoc.is_file():
        pairs = tum.read_associations(assoc)
        rgb = [a for a, _ in pairs]
    else:
        rgb = tum.read_file_list(sp / "rgb.txt")
        depth = tum.read_file_list(sp / "depth.txt") if (sp / "depth.txt").is_file() else []
        max_diff = float(data.get("max_time_diff") or 0.02)
        pairs = [(rgb[i], depth[j]) for i, j in tum.associate([e.timestamp for e in rgb],
                                                               [e.timestamp for e in depth], max_diff)]
    try:
        keep = tum.cut_indices(len(pairs), _int_or(data.get("start"), 0), _int_or(data.get("frames"), 0),
                               _int_or(data.get("stride"), 1), str(sp))
    except DynslamError:
        keep = []
    index = {k: n for n, k in enumerate(keep)}
    out = [_Listed(r.timestamp, r.stamp, sp / r.file, sp / d.file, index.get(k)) for k, (r, d) in enumerate(pairs)]
    paired = {id(r) for r, _ in pairs}
    out += [_Listed(r.timestamp, r.stamp, sp / r.file, None, None) for r in rgb if id(r) not in paired]
    return sorted(out, key=lambda e: e.timestamp)


def _nearest(times: np.ndarray, t: float) -> Optional[int]:
    if times.size == 0:
        return None
    k = int(np.argmin(np.abs(times - t)))
    return k if abs(times[k] - t) <= STAMP_TOL_S else None


@dataclass
class MontageRow:
    stamp: str  # the mask's timestamp (its file name)
    index: Optional[int] = None  # frame index in the run, when the sequence lists it
    files: dict = field(default_factory=dict)  # panel -> the image file shown
    missing: dict = field(default_factory=dict)  # panel -> why nothing is shown


@dataclass
class MontageResult:
    path: Path
    title: str
    rows: list
    depth_max_m: float  # the one depth scale of the figure: 0 … depth_max_m metres


PANELS = ("input RGB", "input depth", "rendered depth", "motion mask")


def _choose(stamps: list[str], frames: Optional[list[str]], indices: Optional[list[int]],
            listed: list[_Listed], mdir: Path, n: int) -> list[str]:
    times = np.array([float(s) for s in stamps])
    chosen = []
    if frames:
        bad = []
        for f in frames:
            k = _nearest(times, float(f)) if _isfloat(f) else None
            (bad.append(f) if k is None else chosen.append(stamps[k]))
        if bad:
            raise DynslamError(f"no mask for frame(s) {', '.join(bad)} in {mdir} "
                               f"(masks at {stamps[0]} … {stamps[-1]}, {len(stamps)} files)")
    if indices:
        by_index = {e.index: e for e in listed if e.index is not None}
        bad = []
        for i in indices:
            k = _nearest(times, by_index[i].timestamp) if i in by_index else None
            (bad.append(str(i)) if k is None else chosen.append(stamps[k]))
        if bad:
            raise DynslamError(f"no mask for frame index(es) {', '.join(bad)} in {mdir} "
                               f"({len(by_index)} frames listed for the run's sequence)")
    if frames or indices:
        return chosen
    return [stamps[i] for i in np.unique(np.linspace(0, len(stamps) - 1, min(n, len(stamps))).astype(int))]


def _inputs_for(run_dir: Path) -> tuple[list[_Listed], str, float]:
    """(listed images, why none when empty, input depth scale) of the run's sequence."""
    sp = runs.sequence_path(run_dir)
    data = runs.read_run_config(run_dir).get("data") or {}
    data = data if isinstance(data, dict) else {}
    scale = float(data.get("depth_scale") or 5000.0)
    if sp is None:
        return [], "sequence folder not in run.json", scale
    if not sp.is_dir():
        return [], f"sequence folder {sp} not found", scale
    if (sp / "synth.json").is_file():
        from dynslam_cli.data.tum import read_synth_json

        try:
            scale = float(read_synth_json(sp / "synth.json").get("depth_scale") or scale)
        except (DynslamError, TypeError, ValueError):
            pass
    try:
        return _sequence_inputs(sp, data), "", scale
    except DynslamError as exc:
        return [], str(exc), scale


def montage_figure(run_dir: Path, frames: Optional[list[str]] = None, n: int = 4,
                   indices: Optional[list[int]] = None):
    """``(figure, MontageResult without path)`` or None when the run saved no masks; the caller closes
    the figure.  ``frames``: mask timestamps (matched numerically); ``indices``: frame indices in the run."""
    import cv2

    run_dir = Path(run_dir)
    mdir = run_dir / "masks"
    stems = [p.stem for p in mdir.glob("*.png")] if mdir.is_dir() else []
    stems = sorted((s for s in stems if _isfloat(s)), key=float)
    if not stems:
        return None
    listed, why, in_scale = _inputs_for(run_dir)
    chosen = _choose(stems, frames, indices, listed, mdir, n)
    ltimes = np.array([e.timestamp for e in listed])

    rows, images = [], []
    for ts in chosen:
        row = MontageRow(ts)
        k = _nearest(ltimes, float(ts))
        e = listed[k] if k is not None else None
        if e is not None:
            row.index = e.index
        cands = {"input RGB": e.rgb if e else None, "input depth": e.depth if e else None,
                 "rendered depth": run_dir / "renders" / f"{ts}_depth.png", "motion mask": mdir / f"{ts}.png"}
        imgs = {}
        for panel, path in cands.items():
            if path is None:
                row.missing[panel] = why or (f"no image listed at t={ts}" if e is None else "no associated depth")
                continue
            img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
            if img is None:
                row.missing[panel] = f"{'not saved' if panel == 'rendered depth' else 'missing'}: {path.name}"
                continue
            row.files[panel] = path
            if panel == "input RGB":
                img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if img.ndim == 3 else img
            elif panel == "motion mask":
                img = (img if img.ndim == 2 else img[..., 0]) > 127
            else:
                img = img.astype(np.float32) / (in_scale if panel == "input depth" else RENDER_DEPTH_SCALE)
            imgs[panel] = img
        rows.append(row)
        images.append(imgs)

    depths = np.concatenate([im[im > 0].ravel() for imgs in images for p, im in imgs.items() if "depth" in p]
                            or [np.zeros(0, np.float32)])
    vmax = float(np.ceil(np.percentile(depths, 99.5) * 2) / 2) if depths.size else 1.0
    vmax = max(vmax, 0.5)

    plt = _plt()
    cmap = plt.get_cmap(DEPTH_CMAP).with_extremes(bad="white")
    fig, axes = plt.subplots(len(chosen), len(PANELS), figsize=(10, 1.95 * len(chosen) + 1.2), dpi=90,
                             squeeze=False, layout="constrained")
    depth_im = None
    for ax_row, row, imgs in zip(axes, rows, images, strict=False):
        size = next((im.shape[:2] for im in imgs.values()), None)
        for ax, panel in zip(ax_row, PANELS, strict=False):
            ax.set_xticks([])
            ax.set_yticks([])
            img = imgs.get(panel)
            head = panel
            if panel == "motion mask" and img is not None:
                head += f" ({100 * img.mean():.0f}% dynamic)"
            ax.set_title(head, fontsize=8)
            if img is None:
                ax.text(0.5, 0.5, row.missing.get(panel, ""), ha="center", va="center", fontsize=6, wrap=True,
                        transform=ax.transAxes)
                continue
            # every panel of a row at the input's size (renders are at the check resolution)
            ext = (0, size[1], size[0], 0) if size else None
            if "depth" in panel:
                depth_im = ax.imshow(np.ma.masked_less_equal(img, 0), cmap=cmap, vmin=0.0, vmax=vmax,
                                     extent=ext, interpolation="nearest")
            elif panel == "motion mask":
                ax.imshow(img, cmap="gray", vmin=0, vmax=1, extent=ext, interpolation="nearest")
            else:
                ax.imshow(img, extent=ext)
        label = f"frame {row.index}\n" if row.index is not None else ""
        ax_row[0].set_ylabel(f"{label}t = {row.stamp}", fontsize=8)
    if depth_im is not None:
        fig.colorbar(depth_im, ax=axes[:, 1:3].ravel().tolist(), location="bottom", shrink=0.8, aspect=40,
                     label="depth (m), blank = no depth")
    title = run_caption(run_dir) if (run_dir / "run.json").is_file() else run_dir.name
    fig.suptitle(title, fontsize=10)
    return fig, MontageResult(Path(), title, rows, vmax)


def make_montage(run_dir: Path, out_png: Path, frames: Optional[list[str]] = None, n: int = 4,
                 indices: Optional[list[int]] = None) -> Optional[MontageResult]:
    """Write the montage PNG (rows: input RGB / input depth / rendered depth / motion mask at the chosen
    mask timestamps, one depth scale with a colour bar); None when the run saved no masks."""
    built = montage_figure(run_dir, frames, n, indices)
    if built is None:
        return None
    fig, res = built
    res.path = _save(fig, out_png)
    return res


def montage(run_dir: Path, out_png: Path, frames: Optional[list[str]] = None, n: int = 4,
            indices: Optional[list[int]] = None) -> Optional[Path]:
    """:func:`make_montage`, returning only the PNG's path (None when no masks)."""
    res = make_montage(run_dir, out_png, frames, n, indices)
    return res.path if res is not None else None


def _isfloat(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False
