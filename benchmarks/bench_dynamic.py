"""Dynamic vs static mode: ATE (beside the still-camera ATE), motion-mask IoU, classifier updates,
fps and per-component ms, on synthetic presets and on the real Bonn crowd clip in ../shared.

    .venv/bin/python benchmarks/bench_dynamic.py                       # the issue's full set (slow: hours on 2 cores)
    .venv/bin/python benchmarks/bench_dynamic.py --presets walker,crowd --frames 80 --size 320x240 --no-bonn
    .venv/bin/python benchmarks/bench_dynamic.py --presets crowd --modes dynamic,dynamic-noreplay --no-bonn ...
    .venv/bin/python benchmarks/bench_dynamic.py --presets "" --device cuda --threads 2 --repeats 3   # the clip on a GPU

Modes: dynamic, static, dynamic-noreplay (replay buffer off: compare classifier updates) and
dynamic-yolo (the yolo-seg segmenter with ../shared/models/yolov8n-seg_deq_fp32.onnx).

``--device`` (default cpu) is every run's device. ``DYNSLAM_SHARED`` names another folder for ../shared.
Runs go to results/bench/dynamic/<case>/<mode>/ (reused when complete, with the same config and code
version, unless --fresh); prints a Markdown table. Use --threads 1 on a busy machine (OpenMP spin makes 2
threads far slower there).

``--repeats N`` runs every case N times in rounds (each round all modes in turn; rounds after the first go to
<mode>-r<k>/), so that speed is compared within one stretch of time (the shared machine drifts by
tens of per cent within an hour): the table gives the median over the rounds of fps and of each
component's median ms, the ATE of the first round (with the range where the rounds differ), and
each round's time per frame over static mode's of the same round.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

from _bench import REPO, SHARED  # sets up the path and the environment

YOLO = SHARED / "models" / "yolov8n-seg_deq_fp32.onnx"
PERSON = REPO / "configs" / "presets" / "yolo-person.yaml"


def overlay_sets(path: Path) -> list[str]:
    """A config overlay file as section.key=value overrides."""
    import yaml

    return [f"{sec}.{k}={json.dumps(v)}" for sec, kv in yaml.safe_load(path.read_text()).items() for k, v in kv.items()]


# --modes names -> config overrides
MODES = {
    "dynamic": ["run.mode=dynamic"],
    "static": ["run.mode=static"],
    "dynamic-noreplay": ["run.mode=dynamic", "motion.replay=false"],
    "dynamic-yolo": ["run.mode=dynamic", "motion.segmenter=yolo-seg", f"motion.segmenter_model={YOLO}"],
    # configs/presets/yolo-person.yaml: the yolo-seg segmenter, people dynamic from the first frame
    "dynamic-yolo-person": ["run.mode=dynamic", f"motion.segmenter_model={YOLO}"] + overlay_sets(PERSON),
}


def run_case(spec: str, mode: str, out: Path, sets: list[str], fresh: bool) -> dict:
    from _bench import run_or_reuse

    from dynslam_cli.eval.ate import evaluate_run_ate
    from dynslam_cli.eval.masks import evaluate_run_masks

    run_or_reuse(spec, sets + MODES[mode] + ["run.save_masks=true"], out, fresh)
    ate = evaluate_run_ate(out, plot=False)
    row = {"case": spec, "mode": mode, "ate_cm": 100 * ate.rmse_m, "still_cm": 100 * ate.rmse_still_m}
    timing = json.loads((out / "timing.json").read_text())
    row["fps"] = timing["fps"]
    row["fps_after_first"] = timing.get("fps_after_first", float("nan"))
    row["updates"] = timing.get("classifier_updates", "—")
    row["median_ms"] = timing["median_ms"]
    # CPU time of every thread per frame, and over the mean frame's wall time: how many cores the run kept busy
    row["cpu_ms"] = timing.get("cpu_ms_per_frame", float("nan"))
    row["cores"] = row["cpu_ms"] / max(timing["mean_ms"].get("frame", float("nan")), 1e-9)
    row["iou"] = "—"
    if mode.startswith("dynamic") and spec.startswith("synth/"):
        m = evaluate_run_masks(out)
        row["iou"] = m.mean_iou_moving
    return row


def aggregate(rounds: list[dict]) -> dict:
    """One case and mode over repeated rounds (``run_case`` rows): medians of the speed figures, the
    first round's accuracy, and the ATE's range over the rounds."""
    first = dict(rounds[0])
    for k in ("fps", "fps_after_first", "cpu_ms", "cores"):
        first[k] = statistics.median(r[k] for r in rounds)
    comps = set().union(*(r["median_ms"] for r in rounds))
    first["median_ms"] = {c: statistics.median(r["median_ms"].get(c, 0.0) for r in rounds) for c in sorted(comps)}
    ates = [r["ate_cm"] for r in rounds]
    first["ate_range_cm"] = (min(ates), max(ates))
    first["rounds"] = len(rounds)
    return first


def round_ratios(rounds: list[list[dict]], mode: str) -> list[float]:
    """Per round, ``mode``'s overall time per frame (1 / fps) over static mode's in the same round
    (rows of one case)."""
    out = []
    for rows in rounds:
        by = {r["mode"]: r for r in rows}
        if mode in by and "static" in by and by[mode]["fps"] > 0:
            out.append(by["static"]["fps"] / by[mode]["fps"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", default="walker,crowd,kidnap,balloon,tracking")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--modes", default="dynamic,static",
                    help=f"comma-separated, of {', '.join(MODES)} (yolo: {YOLO.name} from ../shared/models)")
    ap.add_argument("--no-bonn", action="store_true")
    ap.add_argument("--bonn-frames", type=int, default=150)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--device", choices=("auto", "cpu", "cuda"), default="cpu",
                    help="run.device of every run (cuda runs go to folders named ...-cuda)")
    ap.add_argument("--set", action="append", default=[], help="extra config override (repeatable)")
    ap.add_argument("--data-root", default=str(Path(tempfile.gettempdir()) / "dynslam-bench-data"))
    ap.add_argument("--out", default=str(REPO / "results" / "bench" / "dynamic"))
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("--repeats", type=int, default=1, help="rounds of every case (speed as medians over them)")
    a = ap.parse_args()
    if a.repeats < 1:
        ap.error("--repeats must be at least 1")
    w, h = (int(v) for v in a.size.lower().split("x"))
    base = [f"data.root={a.data_root}", f"run.threads={a.threads}", f"run.device={a.device}"] + a.set
    dev = "" if a.device == "cpu" else f"-{a.device}"
    cases = []
    for p in [p for p in a.presets.split(",") if p]:
        cases.append((f"synth/{p}", base + [f"synth.width={w}", f"synth.height={h}", f"synth.frames={a.frames}"],
                      f"synth-{p}-{w}x{h}-{a.frames}f{dev}"))
    bonn = SHARED / "data" / "bonn_crowd_150_449_s2"
    if not a.no_bonn:
        if bonn.is_dir():
            cases.append((str(bonn), base + [f"data.frames={a.bonn_frames}"], f"bonn-crowd-clip-{a.bonn_frames}f{dev}"))
        else:
            print(f"skipping the Bonn clip: {bonn} is absent", file=sys.stderr)
    modes = [m for m in a.modes.split(",") if m]
    bad = [m for m in modes if m not in MODES]
    if bad:
        ap.error(f"unknown mode(s) {', '.join(bad)}; choose from {', '.join(MODES)}")
    for m in ("dynamic-yolo", "dynamic-yolo-person"):
        if m in modes and not YOLO.is_file():
            ap.error(f"mode {m} needs {YOLO}")
    rows, ratios = [], {}
    for spec, sets, name in cases:
        rounds = []
        for k in range(a.repeats):
            rounds.append([run_case(spec, m, Path(a.out) / name / (m if k == 0 else f"{m}-r{k}"), sets, a.fresh)
                           for m in modes])
        rows += [aggregate([rr[i] for rr in rounds]) for i in range(len(modes))]
        ratios.update({(spec, m): round_ratios(rounds, m) for m in modes if m != "static"})
    comps = ["segment", "encode", "track", "render", "check", "update", "judge", "keyframes", "map", "wait", "frame"]
    if a.repeats > 1:
        print(f"speed: medians over {a.repeats} rounds; ATE: the first round's (range where rounds differ)")
    print("| case | mode | ATE cm | still cm | mask IoU | updates | fps | fps after f0 | CPU ms a frame | cores busy | "
          + " | ".join(comps) + " |")
    print("|---" * (10 + len(comps)) + "|")
    for r in rows:
        iou = f"{r['iou']:.3f}" if isinstance(r["iou"], float) else "—"
        ms = " | ".join(f"{r['median_ms'].get(c, float('nan')):.0f}" if c in r["median_ms"] else "—" for c in comps)
        lo, hi = r["ate_range_cm"]
        ate = f"{r['ate_cm']:.2f}" + (f" ({lo:.2f}–{hi:.2f})" if hi - lo >= 0.005 else "")
        print(f"| {r['case']} | {r['mode']} | {ate} | {r['still_cm']:.2f} | {iou} | {r['updates']} | "
              f"{r['fps']:.2f} | {r['fps_after_first']:.2f} | {r['cpu_ms']:.0f} | {r['cores']:.2f} | {ms} |")
    # the overhead of each dynamic variant over static mode on the same case (median frame; overall time per frame)
    static = {r["case"]: r for r in rows if r["mode"] == "static"}
    for r in rows:
        st = static.get(r["case"])
        if st is not None and r["mode"] != "static" and "frame" in r["median_ms"] and "frame" in st["median_ms"]:
            d, s0 = r["median_ms"]["frame"], st["median_ms"]["frame"]
            per_round = ratios.get((r["case"], r["mode"]), [])
            each = f" (per round x{', x'.join(f'{v:.2f}' for v in per_round)})" if len(per_round) > 1 else ""
            print(f"overhead of {r['mode']} over static on {r['case']}: median frame {d:.0f} vs {s0:.0f} ms "
                  f"(x{d / max(s0, 1e-9):.2f}); overall time per frame x{st['fps'] / max(r['fps'], 1e-9):.2f}{each}; "
                  f"fps {r['fps']:.2f} vs {st['fps']:.2f}; CPU per frame x{r['cpu_ms'] / max(st['cpu_ms'], 1e-9):.2f}")


if __name__ == "__main__":
    main()
