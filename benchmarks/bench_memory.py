"""Peak memory of the default dynamic pipeline and how it grows with the sequence length.

    .venv/bin/python benchmarks/bench_memory.py SEQ [--frames N] [--every 100] [--json PATH]

Runs SEQ (a sequence spec or folder, e.g. one written by `dynslam synth walker --frames 1000`)
through ``run_sequence`` (dynamic mode, one thread, checkpoints as configured) into a run folder
(``--out``, default a temporary folder). A background thread reads /proc/self/statm every 0.5 s;
every ``--every`` frames a row records the resident memory now and its peak since the last row,
with the sizes of what grows: neural-map keyframes and their stored rays, the backend's keyframes,
landmarks and observations, the motion module's keyframe features, and the per-frame logs (tracking
events, classifier-update records).  The growth per 100 frames is a least-squares line over the
second half of the rows.  Sizes are the ``nbytes`` of the numpy arrays in the objects' public
attributes (the mapper gathers each optimisation's rays from the keyframes' own arrays and keeps no
copy of them).

The rows are taken after each frame by wrapping the frame loop's ``FrameLoop.process`` (run/loop.py; the
runner has no per-frame hook); the run itself is unchanged.

Measured at 1927648 (walker preset 640x480, 1000 frames, one thread, 2 busy cores, 1000 first-frame
iterations): peak 1707 MB (mesh extraction included; timing.json's peak_rss_mb says the same), RSS
1412 MB after the last frame, +24 MB per 100 frames over frames 500-1000: the neural-map keyframes
(20 per 100 frames, 15360 rays each: +9.9 MB in their arrays, about as much again in the mapper's
concatenated copy of them, since removed), motion-module keyframe features (+1.6 MB) and backend
landmarks (+0.3 MB, dead rows never dropped; since compacted). At 4df9335, 300 frames, beside the
code before on the same machine: RSS 1252 against 1342 MB, run peak 1493 against 1528 MB, landmark
rows 3287 against 8008 (2238 alive in both). At 7c6d215, 1000 frames: peak 1696 MB (1590 during the
frames), landmark rows 7559 (4046 alive).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
sys.path.insert(0, str(REPO))

PAGE = os.sysconf("SC_PAGE_SIZE")
MB = 2.0 ** 20


def rss_mb() -> float:
    """The process's resident set size now (MiB), from /proc/self/statm."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / MB


class Sampler(threading.Thread):
    """Reads the RSS every ``period`` seconds; ``take_peak`` returns the peak since its last call."""

    def __init__(self, period: float = 0.5):
        super().__init__(daemon=True)
        self.period, self.lock, self.stop = period, threading.Lock(), threading.Event()
        self.peak = self.window = rss_mb()

    def run(self) -> None:
        while not self.stop.wait(self.period):
            self.note(rss_mb())

    def note(self, mb: float) -> None:
        with self.lock:
            self.peak, self.window = max(self.peak, mb), max(self.window, mb)

    def take_peak(self) -> float:
        now = rss_mb()
        self.note(now)
        with self.lock:
            out, self.window = self.window, now
        return out


def arrays_mb(*objs) -> float:
    """MiB of the numpy arrays held in the public attributes of ``objs``."""
    total = 0
    for o in objs:
        if o is None:
            continue
        for k, v in vars(o).items():
            if not k.startswith("_") and isinstance(v, np.ndarray):
                total += v.nbytes
    return total / MB


def snapshot(slam, loop) -> dict:
    """The sizes of what grows with the sequence, through public attributes only."""
    be = slam.backend
    lm = None if be is None else be.lm
    mm = loop.mm
    return {
        "frames_tracked": slam.n_frames,
        "map_keyframes": len(slam.keyframes),
        "keyframe_rays": int(sum(len(k) for k in slam.keyframes)),
        "keyframes_mb": arrays_mb(*slam.keyframes),
        "backend_keyframes": 0 if be is None else len(be.kf_frame),
        "landmarks": 0 if lm is None else len(lm),
        "landmarks_alive": 0 if lm is None else int(lm.n_alive),
        "observations": 0 if lm is None else len(lm.obs_kf),
        "backend_mb": arrays_mb(be, lm),
        "motion_keyframes": len(slam.keyframes.instances()),
        "motion_keyframes_mb": sum(a.nbytes for d in slam.keyframes.instances().values() for a in d.values()) / MB,
        "replay_items": 0 if mm is None else len(mm.replay.items),
        "tracking_events": len(slam.events),
        "update_records": len(loop.records),
    }


def growth_per_100(rows: list[dict], key: str) -> float:
    """Slope (per 100 frames) of ``key`` over the second half of the rows (least squares)."""
    last = rows[-1]["frames"]
    half = [r for r in rows if r["frames"] >= last / 2]
    if len(half) < 2:
        return float("nan")
    x = np.array([r["frames"] for r in half], float)
    y = np.array([r[key] for r in half], float)
    return float(np.polyfit(x, y, 1)[0] * 100)


COLUMNS = [("frames", "frames", "{:d}"), ("rss_mb", "RSS MB", "{:.0f}"), ("peak_mb", "peak MB", "{:.0f}"),
           ("map_keyframes", "map kf", "{:d}"), ("keyframe_rays", "kf rays", "{:d}"),
           ("keyframes_mb", "kf MB", "{:.1f}"), ("backend_keyframes", "backend kf", "{:d}"),
           ("landmarks", "landmarks (alive)", None), ("observations", "observations", "{:d}"),
           ("backend_mb", "backend MB", "{:.2f}"), ("motion_keyframes", "motion kf", "{:d}"),
           ("tracking_events", "events", "{:d}"), ("update_records", "update records", "{:d}"),
           ("s", "s", "{:.0f}")]
GROWTH = ("rss_mb", "keyframes_mb", "keyframe_rays", "map_keyframes", "backend_mb", "landmarks", "observations",
          "motion_keyframes_mb", "tracking_events", "update_records")


def cell(row: dict, key: str, fmt) -> str:
    if key == "landmarks":
        return f"{row['landmarks']} ({row['landmarks_alive']})"
    return fmt.format(row[key])


def table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(h for _, h, _ in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(cell(r, k, f) for k, _, f in COLUMNS) + " |" for r in rows]
    return "\n".join(lines)


def measure(spec: str, frames: int, every: int, out: Path, sets: list[str], progress: bool) -> dict:
    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.data.open import open_sequence
    from dynslam_cli.run import runner
    from dynslam_cli.run.environment import peak_rss_mb
    from dynslam_cli.run.loop import FrameLoop

    cfg = resolve_config(spec, None, ["run.mode=dynamic", "run.threads=1", f"data.frames={frames}"] + sets)
    n = len(open_sequence(spec, cfg, progress=False))
    sampler = Sampler()
    rows: list[dict] = []
    t0 = time.perf_counter()
    process = FrameLoop.process

    def hooked(loop, frame, *args, **kwargs) -> dict:
        res = process(loop, frame, *args, **kwargs)
        done = loop.slam.n_frames
        if done % every == 0 or done == n:
            rows.append({"frames": done, "rss_mb": rss_mb(), "peak_mb": sampler.take_peak(),
                         "s": time.perf_counter() - t0, **snapshot(loop.slam, loop)})
            if progress:
                print(f"\n{done} frames: {rows[-1]['rss_mb']:.0f} MB", file=sys.stderr, flush=True)
        return res

    sampler.start()
    FrameLoop.process = hooked
    try:
        res = runner.run_sequence(spec, cfg, out_dir=out, overwrite=True, progress=progress)
    finally:
        FrameLoop.process = process
        sampler.stop.set()
        sampler.join()
    return {"sequence": spec, "frames": res.frames, "every": every, "fps": res.fps, "rows": rows,
            "peak_rss_mb_frames": max((r["peak_mb"] for r in rows), default=0.0),
            "peak_rss_mb": max(sampler.peak, peak_rss_mb()),  # includes the final BA and the mesh
            "growth_per_100_frames": {k: growth_per_100(rows, k) for k in GROWTH} if rows else {},
            "run_dir": str(out)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", help="sequence spec or folder (e.g. /tmp/mem/walker1000 from `dynslam synth`)")
    ap.add_argument("--frames", type=int, default=0, help="frames to run (0 = all)")
    ap.add_argument("--every", type=int, default=100, help="a table row every this many frames")
    ap.add_argument("--out", type=Path, default=None, help="run folder (default: a temporary one, deleted)")
    ap.add_argument("--set", dest="sets", action="append", default=[], help="config override section.key=value")
    ap.add_argument("--json", type=Path, default=None, help="write the rows and the growth here")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    a = ap.parse_args()
    if a.every < 1 or a.frames < 0:
        ap.error("--every must be >= 1 and --frames >= 0")
    from dynslam_cli.utils.io import write_json_atomic

    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        out = a.out if a.out is not None else Path(tmp) / "run"
        r = measure(a.seq, a.frames, a.every, out, a.sets, not a.quiet)
    print(table(r["rows"]))
    print(f"\npeak RSS {r['peak_rss_mb']:.0f} MB over the whole run (final BA and mesh included), "
          f"{r['peak_rss_mb_frames']:.0f} MB during the frames; {r['frames']} frames at {r['fps']:.2f} fps")
    print("growth per 100 frames (second half): " + ", ".join(
        f"{k} {v:+.3g}" for k, v in r["growth_per_100_frames"].items()))
    if a.json is not None:
        write_json_atomic(a.json, r)
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
