"""Dynamic mode with the next frame segmented and encoded beside the current one (run/ahead.py, what
``dynslam run`` does with 2 or more threads) against the same work in order, and static mode beside
them, in alternating rounds of one process.

    .venv/bin/python benchmarks/bench_ahead.py [--frames 150] [--rounds 2] [--threads 2] [--seq PATH]

Each round runs the three in turn (static, dynamic in order, dynamic ahead) on the Bonn clip in
../shared (else a rendered synthetic walker scene, 640x480), each from a fresh SLAM system through the
library's frame loop, frames read ahead in all three.  Prints per round and as medians: wall seconds
(the first frame's included), fps, ms per frame of each component (means; ``wait``: the loop waiting
for the frame read or worked on ahead), the dynamic / static time per frame, and whether both dynamic
variants gave the same trajectory (they must: the work ahead depends on the frame's pixels alone).
The machine is shared and noisy: compare rows of one round, and the medians of one run.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
import tempfile
import time
from pathlib import Path

from _bench import SHARED  # sets up the path and the environment

BONN = SHARED / "data" / "bonn_crowd_150_449_s2"
VARIANTS = ("static", "dynamic in order", "dynamic ahead")
COMPONENTS = ("segment", "encode", "track", "render", "check", "update", "judge", "keyframes", "map", "wait")


def sequence(path: str, frames: int, tmp: str):
    from dynslam_cli.config.resolve import resolve_config

    if not path:
        if BONN.is_dir():
            path = str(BONN)
        else:
            from dynslam_cli.synth.config import SynthConfig
            from dynslam_cli.synth.render import render_preset

            print(f"{BONN} is absent: a synthetic walker scene instead", file=sys.stderr)
            path = str(Path(tmp) / "walker")
            render_preset("walker", Path(path), SynthConfig(width=640, height=480, frames=frames, seed=0),
                          progress=False)
    return path, resolve_config(path, None, [f"data.frames={frames}"])


def run_once(path: str, cfg, variant: str, threads: int) -> dict:
    """One pass over the sequence through FrameLoop; wall time, fps, component means, trajectory."""
    import numpy as np

    from dynslam_cli.data.open import open_sequence
    from dynslam_cli.run.ahead import ReadAhead
    from dynslam_cli.run.loop import FrameLoop
    from dynslam_cli.run.runner import select_device, sequence_bounds
    from dynslam_cli.slam.system import SLAM
    from dynslam_cli.utils.threads import seed_everything, set_threads

    cfg = copy.deepcopy(cfg)
    cfg.run.mode = "static" if variant == "static" else "dynamic"
    set_threads(threads)
    seed_everything(int(cfg.run.seed))
    seq = open_sequence(path, cfg, progress=False)
    device = select_device(cfg.run.device)
    slam = SLAM(cfg, seq.intrinsics, device, bounds=sequence_bounds(cfg, seq), depth_noise=seq.depth_noise)
    loop = FrameLoop(cfg, seq.intrinsics, slam, device, None)
    ahead = ReadAhead(seq, 0, len(seq), loop.perceive if variant == "dynamic ahead" else None)
    sums = dict.fromkeys(COMPONENTS, 0.0)
    t0 = time.perf_counter()
    for i, frame, seen in ahead:
        step = loop.process(frame, seq.stamps[i], seen)
        step["wait"] = ahead.waited_ms
        for k in COMPONENTS:
            sums[k] += float(step.get(k, 0.0))
    wall = time.perf_counter() - t0
    n = len(seq)
    return {"variant": variant, "wall_s": wall, "fps": n / wall, "frame_ms": 1e3 * wall / n,
            "ms": {k: v / n for k, v in sums.items()}, "traj": np.asarray(slam.trajectory())}


def row(r: dict, static_ms: float) -> str:
    ms = " | ".join(f"{r['ms'][k]:.0f}" for k in COMPONENTS)
    return (f"| {r['variant']} | {r['wall_s']:.1f} | {r['fps']:.2f} | {r['frame_ms']:.0f} | {ms} | "
            f"{r['frame_ms'] / static_ms:.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seq", default="", help="a sequence (default: the Bonn clip in ../shared)")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    import numpy as np

    with tempfile.TemporaryDirectory() as tmp:
        path, cfg = sequence(a.seq, a.frames, tmp)
        head = ("| variant | wall s | fps | ms/frame | " + " | ".join(COMPONENTS) + " | / static |\n"
                + "|---" * (5 + len(COMPONENTS)) + "|")
        print(f"sequence {path}, {a.frames} frames, {a.threads} threads, {a.rounds} rounds")
        rounds = []
        for k in range(a.rounds):
            res = {v: run_once(path, cfg, v, a.threads) for v in VARIANTS}
            same = np.array_equal(res["dynamic in order"]["traj"], res["dynamic ahead"]["traj"])
            print(f"\nround {k + 1} (dynamic trajectories identical: {same})\n{head}")
            for v in VARIANTS:
                print(row(res[v], res["static"]["frame_ms"]))
            rounds.append(res)
    print(f"\nmedians over {a.rounds} rounds\n{head}")
    static_ms = statistics.median(r["static"]["frame_ms"] for r in rounds)
    for v in VARIANTS:
        med = {"variant": v, "wall_s": statistics.median(r[v]["wall_s"] for r in rounds),
               "ms": {k: statistics.median(r[v]["ms"][k] for r in rounds) for k in COMPONENTS}}
        med["frame_ms"] = 1e3 * med["wall_s"] / a.frames
        med["fps"] = a.frames / med["wall_s"]
        print(row(med, static_ms))
    gain = [r["dynamic in order"]["wall_s"] / r["dynamic ahead"]["wall_s"] for r in rounds]
    print(f"\ndynamic in order / ahead, wall time per round: {', '.join(f'{g:.2f}' for g in gain)}")


if __name__ == "__main__":
    main()
