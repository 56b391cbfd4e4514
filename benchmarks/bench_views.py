"""The Bonn crowd clip seen four ways: as recorded, played backwards, and at half its frame rate (both phases).

    .venv/bin/python benchmarks/bench_views.py                                   # dynamic mode, seeds 0-2, all views
    .venv/bin/python benchmarks/bench_views.py --views reversed --seeds 0 --presets ",yolo-person" --threads 1

The clip is one real sequence, and its defaults were measured on it. These views ask how they hold where the
clip is easy:
- ``forward``: the clip as recorded (150 frames at about 15 Hz); no one is in view for its first 40 frames, so
  the map and the classifier start on a static room.
- ``reversed``: the same frames in reverse order (time stamps mirrored, the ground truth with them). The run
  starts in the crowd, with three people over most of the image and the camera panning fast: the map, the
  backend's first landmarks and the classifier all start on moving people, as on a sequence that opens amid movers.
- ``half0`` / ``half1``: every 2nd frame, from frame 0 / 1 (``data.stride=2``; about 7.5 Hz): twice the motion
  between frames.

The reversed view is written as symbolic links and re-stamped lists in a temporary folder (``--views-dir`` keeps it);
nothing is copied. Each run goes to <out>/<view>/<preset>/<mode>-s<seed>/ (reused when complete, with the same
config and code version, unless --fresh). Prints a Markdown table: ATE cm of traj_est.txt, the still camera's,
the worst frame's error, classifier updates, fps.
``yolo-person`` needs ../shared/models/yolov8n-seg_deq_fp32.onnx.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

from _bench import REPO, SHARED, run_or_reuse  # sets up the path and the environment

BONN = SHARED / "data" / "bonn_crowd_150_449_s2"
YOLO = SHARED / "models" / "yolov8n-seg_deq_fp32.onnx"
VIEWS = ("forward", "reversed", "half0", "half1")
LISTS = ("rgb.txt", "depth.txt", "groundtruth.txt")


def _entries(path: Path) -> tuple[list[str], list[tuple[float, str]]]:
    """A TUM list's comment lines and its (time stamp, rest of the line) entries."""
    head, rows = [], []
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            head.append(line)
            continue
        stamp, rest = line.split(maxsplit=1)
        rows.append((float(stamp), rest))
    return head, rows


def reversed_view(src: Path, dst: Path) -> Path:
    """``src`` (a TUM/Bonn-layout sequence: rgb.txt, depth.txt, groundtruth.txt) played backwards, in ``dst``:
    every time stamp t becomes t_first + t_last - t (over all three lists, so the images and the ground truth stay
    paired), the lists sorted again, the image folders linked to the originals."""
    lists = {name: _entries(src / name) for name in LISTS}
    stamps = [t for _, rows in lists.values() for t, _ in rows]
    mirror = min(stamps) + max(stamps)
    dst.mkdir(parents=True, exist_ok=True)
    for name, (head, rows) in lists.items():
        flipped = sorted((mirror - t, rest) for t, rest in rows)
        text = "\n".join(head + [f"# played backwards: t -> {mirror:.6f} - t"] + [f"{t:.6f} {rest}" for t, rest in flipped])
        (dst / name).write_text(text + "\n")
    for folder in ("rgb", "depth"):
        link = dst / folder
        if not link.exists():
            os.symlink(src / folder, link, target_is_directory=True)
    return dst


def view_spec(view: str, views_dir: Path) -> tuple[str, list[str]]:
    """The sequence path and config overrides of ``view``."""
    if view == "forward":
        return str(BONN), []
    if view == "reversed":
        return str(reversed_view(BONN, views_dir / "bonn_crowd_reversed")), []
    return str(BONN), ["data.stride=2", f"data.start={int(view[-1])}"]


def summarise(run_dir: Path, spec: str) -> dict:
    """The run's ATE against ``spec``'s ground truth (a reused run's may name a temporary folder long gone)."""
    from dynslam_cli.eval.ate import evaluate_run_ate

    res = evaluate_run_ate(run_dir, gt=Path(spec) / "groundtruth.txt", plot=False)
    timing = json.loads((run_dir / "timing.json").read_text())
    return {"ate": res.rmse_m * 100, "still": res.rmse_still_m * 100, "worst": res.max_m * 100,
            "updates": timing.get("classifier_updates", 0), "fps": timing["fps"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", default=",".join(VIEWS), help=f"comma-separated, of {', '.join(VIEWS)}")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--presets", default="", help='comma-separated presets; "" = the defaults (e.g. ",yolo-person")')
    ap.add_argument("--mode", choices=("dynamic", "static"), default="dynamic")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--set", action="append", default=[], help="extra config override (repeatable)")
    ap.add_argument("--views-dir", default="", help="where the reversed view is written (default: a temporary folder)")
    ap.add_argument("--out", default=str(REPO / "results" / "bench" / "views"))
    ap.add_argument("--fresh", action="store_true")
    a = ap.parse_args()
    if not BONN.is_dir():
        print(f"skipping: the Bonn clip {BONN} is absent (set DYNSLAM_SHARED to the folder holding data/)", file=sys.stderr)
        return
    views = [v for v in a.views.split(",") if v]
    bad = [v for v in views if v not in VIEWS]
    if bad:
        ap.error(f"unknown view(s) {', '.join(bad)}; choose from {', '.join(VIEWS)}")
    presets = a.presets.split(",") if a.presets else [""]
    if "yolo-person" in presets and not YOLO.is_file():
        ap.error(f"the yolo-person preset needs {YOLO}")
    seeds = [int(s) for s in a.seeds.split(",") if s]
    tmp = None if a.views_dir else tempfile.TemporaryDirectory(prefix="dynslam-views-")
    views_dir = Path(a.views_dir or tmp.name)
    rows = []
    try:
        for view in views:
            spec, sets = view_spec(view, views_dir)
            for preset in presets:
                for seed in seeds:
                    out = Path(a.out) / view / (preset or "defaults") / f"{a.mode}-s{seed}"
                    run_sets = sets + [f"run.mode={a.mode}", f"run.seed={seed}", f"run.threads={a.threads}"] + a.set
                    if preset == "yolo-person":
                        run_sets.append(f"motion.segmenter_model={YOLO}")
                    run_or_reuse(spec, run_sets, out, a.fresh, preset=preset or None)
                    rows.append((view, preset or "defaults", seed, summarise(out, spec)))
    finally:
        if tmp is not None:
            tmp.cleanup()
    print(f"{a.mode} mode, {a.threads} thread(s); ATE cm of traj_est.txt")
    print("| view | preset | seed | ATE cm | still camera cm | worst frame cm | classifier updates | fps |")
    print("|---|---|---|---|---|---|---|---|")
    for view, preset, seed, r in rows:
        cells = [view, preset, str(seed), f"{r['ate']:.2f}", f"{r['still']:.2f}", f"{r['worst']:.1f}", str(r["updates"]),
                 f"{r['fps']:.2f}"]
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
