"""Helpers shared by the benchmark scripts (not a benchmark itself: `make bench` runs bench_*.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path


def run_or_reuse(spec: str, sets: list[str], out: Path, fresh: bool) -> dict:
    """Run ``spec`` with config overrides ``sets`` into ``out`` unless a completed run is already
    there (``fresh``: delete and redo it; a failed or interrupted run there is replaced); returns the
    run's run.json."""
    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.run.runner import run_sequence

    done = out / "run.json"
    if fresh and out.exists():
        shutil.rmtree(out)
    if not (done.is_file() and json.loads(done.read_text()).get("status") == "completed"):
        cfg = resolve_config(spec, None, sets)
        run_sequence(spec, cfg, out_dir=out, overwrite=True, progress=True)
    return json.loads(done.read_text())
