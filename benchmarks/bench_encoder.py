"""The instance encoder in other precisions: time per batch against how much the embeddings move.

    .venv/bin/python benchmarks/bench_encoder.py                      # crops of the Bonn clip
    .venv/bin/python benchmarks/bench_encoder.py --seqs /data/synth/crowd_s0,bonn --step 10 --threads 2

Cuts every ``--step``-th frame of each sequence into the geometric segmenter's segments and crops
them as a run does (``motion.encoder_input_size`` 0: 160 px; the run's margin and fill), then encodes the crops
with EfficientNet-Lite0 as

- ``onnx-fp32``: onnxruntime on the cached export (the run's encoder where OpenVINO is not installed):
  the reference;
- ``openvino-fp32``: the run's encoder, OpenVINO on the same export, in compiled batches of 4 and 1;
- ``onnx-int8``: the same graph statically quantised by onnxruntime (QDQ, int8 weights per channel,
  uint8 activations), calibrated on the other half of the crops (its best case: the test's own data);
- ``torch-fp32`` and ``torch-bf16`` (channels-last; bf16 by autocast, fast only on CPUs with AMX).

Prints per variant the median ms per batch of ``--batch`` crops on ``--threads`` threads, the cosine
of each crop's embedding to the reference (minimum, 5th percentile, median) and how often a crop's
nearest other crop is the reference's (a stand-in for the classifier's decisions, which are
learnt on these embeddings online and so cannot be compared frame by frame).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared"))
BONN = SHARED / "data" / "bonn_crowd_150_449_s2"


def agreement(ref: np.ndarray, emb: np.ndarray) -> dict:
    """How far embeddings ``emb`` (N×D) are from ``ref`` (N×D, the same crops): per-crop cosine
    (min / p5 / median) and the fraction of crops whose nearest other crop (cosine) is the same."""
    a = ref / np.linalg.norm(ref, axis=1, keepdims=True)
    b = emb / np.linalg.norm(emb, axis=1, keepdims=True)
    cos = (a * b).sum(1)

    def nearest(x):
        s = x @ x.T
        np.fill_diagonal(s, -np.inf)
        return s.argmax(1)

    same = float((nearest(a) == nearest(b)).mean()) if len(a) > 1 else float("nan")
    return {"cos_min": float(cos.min()), "cos_p5": float(np.percentile(cos, 5)),
            "cos_median": float(np.median(cos)), "nn_same": same}


def crops_of(path: Path, step: int, size: int) -> np.ndarray:
    """Normalised encoder inputs (N×3×size×size float32) of the segments of every ``step``-th frame."""
    from _bench import segment_crops

    from dynslam_cli.motion.encode_base import normalise_batch
    from dynslam_cli.motion.encode_effnet import MEAN, STD

    out = [normalise_batch(c, MEAN, STD) for c in segment_crops(str(path), step, size=size)[0] if len(c)]
    return np.concatenate(out) if out else np.zeros((0, 3, size, size), np.float32)


def timed(fn, x: np.ndarray, batch: int, reps: int) -> tuple[float, np.ndarray]:
    """Median ms of ``fn`` on the first ``batch`` rows (after one warm-up), and ``fn`` of all rows."""
    xb = x[:batch]
    fn(xb)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn(xb)
        ts.append((time.perf_counter() - t0) * 1000)
    full = np.concatenate([fn(x[i:i + batch]) for i in range(0, len(x), batch)])
    return statistics.median(ts), full


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seqs", default="bonn", help="comma-separated: bonn or sequence folders")
    ap.add_argument("--step", type=int, default=7, help="every STEP-th frame")
    ap.add_argument("--batch", type=int, default=16, help="crops per timed call")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--size", type=int, default=0, help="crop side; 0 = the config default (160)")
    args = ap.parse_args()

    import onnxruntime as ort
    import torch
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    from dynslam_cli.motion.encode_effnet import CONFIG_INPUT, build_model, export_onnx

    size = args.size or CONFIG_INPUT
    parts = []
    for spec in args.seqs.split(","):
        if spec == "bonn" and not BONN.is_dir():
            print(f"skipped bonn: the Bonn clip is not at {BONN} (set DYNSLAM_SHARED)", flush=True)
            continue
        path = BONN if spec == "bonn" else Path(spec)
        if not path.is_dir():
            raise SystemExit(f"no sequence at {path}")
        parts.append(crops_of(path, args.step, size))
        print(f"{path.name}: {len(parts[-1])} crops", flush=True)
    if not parts:
        return
    x = np.concatenate(parts)
    if len(x) < 2 * args.batch:
        raise SystemExit(f"only {len(x)} crops: lower --step or --batch")
    rng = np.random.default_rng(0)
    order = rng.permutation(len(x))
    calib, test = x[order[: len(x) // 2]], x[order[len(x) // 2:]]

    torch.set_num_threads(args.threads)
    so = ort.SessionOptions()
    so.intra_op_num_threads, so.inter_op_num_threads = args.threads, 1
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        fp32 = export_onnx(Path(tmp) / "fp32.onnx", size)
        quant_pre_process(str(fp32), str(Path(tmp) / "pre.onnx"))

        class Calib(CalibrationDataReader):
            def __init__(self):
                self.it = iter([{"images": calib[i:i + 8]} for i in range(0, len(calib), 8)])

            def get_next(self):
                return next(self.it, None)

        int8 = Path(tmp) / "int8.onnx"
        quantize_static(str(Path(tmp) / "pre.onnx"), str(int8), Calib(), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True)
        sessions = {name: ort.InferenceSession(str(p), sess_options=so, providers=["CPUExecutionProvider"])
                    for name, p in (("onnx-fp32", fp32), ("onnx-int8", int8))}
        model = build_model(size).to(memory_format=torch.channels_last)

        def torch_run(xb, bf16=False):
            with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                xt = torch.from_numpy(np.ascontiguousarray(xb)).to(memory_format=torch.channels_last)
                return model(xt)[0].float().numpy()

        def ort_run(name):
            return lambda xb: sessions[name].run(["features"], {"images": xb})[0]

        variants = {"onnx-fp32": ort_run("onnx-fp32")}
        try:
            from dynslam_cli.motion.openvino_utils import OvBatches

            ov = OvBatches(fp32, (3, size, size), ("features",), args.threads)
            variants["openvino-fp32"] = lambda xb: ov.run(xb)[0]
        except ImportError:
            print("openvino-fp32 skipped: OpenVINO is not installed (pip install openvino)", flush=True)
        variants["onnx-int8"] = ort_run("onnx-int8")
        variants["torch-fp32"] = torch_run
        variants["torch-bf16"] = lambda xb: torch_run(xb, bf16=True)
        ref = None
        for name, fn in variants.items():
            ms, emb = timed(fn, test, args.batch, args.reps)
            ref = emb if ref is None else ref
            rows.append((name, ms, agreement(ref, emb)))

    print(f"\n{len(test)} test crops ({len(calib)} calibrate int8), {size} px, batch {args.batch}, "
          f"{args.threads} thread(s)\n")
    print("| variant | ms per batch | ratio | cos min | cos p5 | cos median | same nearest crop |")
    print("|---|---|---|---|---|---|---|")
    base = rows[0][1]
    for name, ms, a in rows:
        print(f"| {name} | {ms:.1f} | {ms / base:.2f} | {a['cos_min']:.3f} | {a['cos_p5']:.3f} | "
              f"{a['cos_median']:.4f} | {a['nn_same']:.3f} |")


if __name__ == "__main__":
    main()
