"""Helpers shared by the benchmark scripts (not a benchmark itself: `make bench` runs bench_*.py)."""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path

# importing this module sets a script up: the repository on the path, no display for matplotlib, no onnxruntime
# telemetry, and where the real data and weights are (../shared unless DYNSLAM_SHARED names another folder)
REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))
SHARED = Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared"))


def run_or_reuse(spec: str, sets: list[str], out: Path, fresh: bool, preset: str | None = None) -> dict:
    """Run ``spec`` with config overrides ``sets`` (over the named ``preset``, if any) into ``out`` unless
    a completed run is already there (``fresh``: delete and redo it; a failed or interrupted run there is
    replaced); returns the run's run.json."""
    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.run.runner import run_sequence

    done = out / "run.json"
    if fresh and out.exists():
        shutil.rmtree(out)
    cfg = resolve_config(spec, None, sets, preset=preset)
    meta = json.loads(done.read_text()) if done.is_file() else {}
    if meta.get("status") == "completed":
        why = stale_run(out, cfg, meta)
        if why is None:
            return meta
        print(f"redoing {out}: {why}", file=sys.stderr)
    run_sequence(spec, cfg, out_dir=out, overwrite=True, progress=True)
    return json.loads(done.read_text())


def stale_run(out: Path, cfg, meta: dict) -> str | None:
    """Why the completed run in ``out`` (``meta``: its run.json) does not stand for config ``cfg`` with this code
    (its config.yaml differs in a key other than where files live, or ``meta`` names another code version); None
    when it does.  Without this, a second ``--set run.seed=2`` into the same folder would report the first run."""
    from dynslam_cli.config.loader import config_from_file, config_to_dict
    from dynslam_cli.errors import DynslamError
    from dynslam_cli.run.checkpoint import code_version, differing_keys, flatten

    try:
        old = flatten(config_to_dict(config_from_file(out / "config.yaml")))
    except (OSError, DynslamError) as exc:
        return f"its config.yaml does not read ({exc})"
    new = flatten(config_to_dict(cfg))
    diff = differing_keys(old, new)
    if diff:
        return f"config key {diff[0]} differs (there {old.get(diff[0])!r}, asked {new.get(diff[0])!r})"
    was = meta.get("versions", {}).get("dynslam")
    if was != code_version():
        return f"code version differs (there {was}, now {code_version()})"
    return None


def segment_crops(spec: str, step: int = 1, frames: int = 0, size: int = 0):
    """The crops a run encodes: every ``step``-th frame of ``spec`` (its first ``frames``; 0 = all) cut
    into the geometric segmenter's segments and cropped with the run's margin and fill at ``size`` px
    (0: ``motion.encoder_input_size``, else EfficientNet-Lite0's).  Returns (per such frame a
    (K, size, size, 3) uint8 array, the resolved config)."""
    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.data.open import open_sequence
    from dynslam_cli.motion.encode_base import CROP_BACKGROUND, CROP_MARGIN, masked_crops
    from dynslam_cli.motion.encode_effnet import CONFIG_INPUT, MEAN, crop_fill
    from dynslam_cli.motion.segment_geometric import GeometricSegmenter

    cfg = resolve_config(spec, None, [f"data.frames={frames}"] if frames > 0 else [])
    seq = open_sequence(spec, cfg)
    seg = GeometricSegmenter.from_config(cfg.motion, seq.intrinsics)
    fill = crop_fill(MEAN, CROP_BACKGROUND)
    size = size or cfg.motion.encoder_input_size or CONFIG_INPUT
    return [masked_crops(f.rgb, seg.segment(f.rgb, f.depth).ids, size, CROP_MARGIN, fill)
            for f in seq if f.index % step == 0], cfg
