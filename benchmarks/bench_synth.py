"""Benchmark of the synthetic scene renderer: seconds per preset and size.

Renders each case into a temporary folder (median over a few repeats where cheap) and prints a
table: preset, frames, size, seconds, s/frame.  The numba kernel is compiled (or loaded from its
cache) by a tiny warm-up render first, so the table shows steady-state cost.

    .venv/bin/python benchmarks/bench_synth.py [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import dynslam_cli.config  # noqa: E402,F401  (import order: config before synth.config)
from dynslam_cli.synth.config import SynthConfig  # noqa: E402
from dynslam_cli.synth.render import render_preset  # noqa: E402

CASES = [  # preset, frames, (width, height), repeats
    ("walker", 100, (640, 480), 3),
    ("static", 30, (640, 480), 1),
    ("crowd", 30, (640, 480), 1),
    ("kidnap", 30, (640, 480), 1),
    ("balloon", 30, (640, 480), 1),
    ("tracking", 30, (640, 480), 1),
    ("walker", 30, (320, 240), 3),
]
QUICK = [("walker", 20, (320, 240), 1), ("crowd", 10, (320, 240), 1)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="Two small cases only.")
    args = ap.parse_args()
    cases = QUICK if args.quick else CASES
    with tempfile.TemporaryDirectory(prefix="bench_synth_") as tmp:
        t0 = time.perf_counter()
        render_preset("walker", Path(tmp) / "warmup", SynthConfig(width=32, height=24), frames=2, progress=False)
        print(f"warm-up (numba compile or cache load): {time.perf_counter() - t0:.1f} s")
        rows = []
        for preset, frames, (w, h), reps in cases:
            times = []
            for r in range(reps):
                res = render_preset(preset, Path(tmp) / f"{preset}_{r}", SynthConfig(width=w, height=h),
                                    frames=frames, progress=False)
                times.append(res.seconds)
            sec = statistics.median(times)
            rows.append((preset, frames, f"{w}x{h}", sec, sec / frames, reps))
        if not args.quick:
            # The whole command as a user runs it (interpreter start, imports, numba cache load).
            cmd = [sys.executable, "-m", "dynslam_cli.cli", "synth", "walker", "--frames", "100",
                   "--size", "640x480", "--out", str(Path(tmp) / "cli"), "-q"]
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, cwd=Path(__file__).resolve().parents[1], stdout=subprocess.DEVNULL)
            sec = time.perf_counter() - t0
            rows.append(("walker (dynslam synth CLI)", 100, "640x480", sec, sec / 100, 1))
    print(f"{'preset':<27} {'frames':>6} {'size':>8} {'seconds':>8} {'s/frame':>8} {'repeats':>7}")
    for preset, frames, size, sec, per, reps in rows:
        print(f"{preset:<27} {frames:>6} {size:>8} {sec:>8.2f} {per:>8.3f} {reps:>7}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
