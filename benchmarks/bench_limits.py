"""How far each part of a default run is from what the hardware allows (issue 21, "Speed").

    .venv/bin/python benchmarks/bench_limits.py [--reps 10] [--threads 2] [--device cpu|cuda] [--json PATH]

The same run first measures this machine's peaks at the thread count used: float32 matmul GFLOP/s
(2048x2048 ``torch.mm``) and memory copy GB/s (a 256 MB tensor copied, read + write bytes counted),
both the median of ``--reps``.  Then every component runs the library's own code on inputs of the
sizes a default run uses (640x480, configs/base.yaml through the Bonn dataset config; the first
frames of ../shared/data/bonn_crowd_150_449_s2 when present, else a rendered synthetic walker scene),
and one row gives:

* ``ms``: the median wall time over ``--reps`` after warm-up;
* ``GFLOP``: matmul and convolution FLOPs counted by ``torch.utils.flop_counter.FlopCounterMode``
  (forward and backward), plus the hand models below for what torch does not see (the numba hash
  grid, the one-blob encoding; elementwise torch ops are left out: at a few FLOPs per byte they are
  bound by their bytes);
* ``MB``: bytes moved.  Torch code: every aten op reads its tensor operands from memory and writes
  its results (views move nothing; an in-place op reads and writes its operand, a fill or copy only
  writes it) -- the traffic of the op sequence as written, not of a fused re-design.  The numba hash
  grid: per point 8 corners x levels x features x 4 B gathered (the table gradient scatters them back:
  read + write), plus points, outputs, the stored Jacobian and the zero-filled table gradient.  The
  EfficientNet encoder: each convolution / linear layer's weights, input and output once (batch norm
  and activations folded into it, as onnxruntime runs it);
* ``floor ms`` = max(GFLOP / peak GFLOP/s, MB / peak GB/s): the time the part would take at the
  measured peaks; ``x floor`` = ms / floor ms: how many times slower than that the part runs; ``bound``:
  which of the two floors is larger (``bytes`` = memory traffic, ``flops`` = arithmetic), ``-`` where
  only a bytes floor exists (no sensible FLOP model: ORB, gtsam).

Reading it: a ratio near 1-3 is at the hardware's limit (only less work would help); tens or more
means overheads (Python, small launches, threads idling, caches missed by scattered reads) dominate,
and the row's note says which.  The bandwidth is that of a copy far larger than the caches; a part
whose working set stays in cache can run faster than its bytes floor, so a ratio below 1 says
"cache-resident", not "faster than the hardware".  (On the 2-core dev machine smaller copies were
slower, not faster: 2 GB/s at 8 MB against 8-10 at 256 MB.)  On a shared machine the medians are
noisy: compare rows of one run, not runs.

CPU-side parts (ORB, the pose optimisation, bundle adjustment) are always compared
with the CPU peaks; with ``--device cuda`` the map's parts and the encoder run on the GPU (the hash grid on its torch
path, whose ops the byte count then sees directly) and are compared with the GPU peaks, measured the
same way in the same run.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared"))
BONN = SHARED / "data" / "bonn_crowd_150_449_s2"
FRAMES = 40  # frames read for the backend's inputs (a local bundle adjustment happens within them)
MATMUL_N = 2048
COPY_MB = 256  # the floor's bandwidth: a copy far beyond the caches (DRAM)
POSE_ROUNDS = 4  # dynslam_cli.backend.tracking.optimize_pose's default rounds
# float ops per observation of one Gauss-Newton iteration of the pose-only optimisation: residual (~40),
# Jacobian (~30), J^T W J (6x3x6 multiply-adds x 2 = 216) and J^T W e (36)
POSE_FLOPS_PER_OBS = 330
# aten ops that move no bytes (allocation, aliasing, reading a scalar)
NO_TRAFFIC = {"aten::empty", "aten::empty_strided", "aten::empty_like", "aten::detach", "aten::lift_fresh",
              "aten::alias", "aten::_local_scalar_dense", "aten::set_", "aten::resize_"}
# in-place ops that only write their operand (no read of it)
WRITE_ONLY = {"aten::zero_", "aten::fill_", "aten::copy_", "aten::uniform_", "aten::normal_", "aten::random_",
              "aten::bernoulli_", "aten::exponential_"}


# ---------------------------------------------------------------------------------------------- cost models
@dataclass(frozen=True)
class Cost:
    """Float operations and bytes moved by one call of a component."""

    flops: float = 0.0
    bytes: float = 0.0

    def __add__(self, other: "Cost") -> "Cost":
        return Cost(self.flops + other.flops, self.bytes + other.bytes)


def hashgrid_forward_cost(n: int, levels: int, features: int, jac: bool = False) -> Cost:
    """Forward of the hash grid on ``n`` points.  FLOPs per point and level: position and fraction (6),
    the 1 - f terms (3), the 8 corner weights (2 multiplies each), the weighted sums (8 x features
    multiply-adds); with ``jac`` the stored Jacobian (per feature and axis 4 corner pairs x 4 + 1).
    Bytes per point: the point (12 B), 8 corners x levels x features x 4 B gathered, the output, and
    with ``jac`` the Jacobian written (levels x features x 3 x 4 B)."""
    per_level = 25 + 16 * features + (51 * features if jac else 0)
    out = levels * features * 4
    gathered = 8 * out
    byt = 12 + gathered + out + (3 * out if jac else 0)
    return Cost(float(n * levels * per_level), float(n * byt))


def hashgrid_backward_cost(n: int, levels: int, features: int, table_size: int, table: bool, x: bool,
                           jac: bool = False) -> Cost:
    """Backward of the hash grid on ``n`` points (``table``: the table gradient; ``x``: the point
    gradient, from the stored Jacobian when ``jac``, else recomputed from the gathered corners).
    Bytes per point: the point and the output gradient read; the table gradient scatters 8 corners x
    levels x features x 4 B back (read + write) into a zero-filled levels x table x features x 4 B
    table; the point gradient reads the corners again (or the Jacobian) and writes 12 B (through a
    levels x 3 x 4 B partial, written and read, without the Jacobian)."""
    out = levels * features * 4
    flops = 0.0
    byt = 12.0 + out  # points, output gradient
    fixed = 0.0
    if jac and x and not table:
        flops += n * levels * 6 * features
        byt += 3 * out + 12
    else:
        flops += n * levels * 25  # the corner weights, recomputed
        if table:
            flops += n * levels * 16 * features
            byt += 2 * 8 * out
            fixed += levels * table_size * features * 4
        if x:
            flops += n * levels * (51 * features + 3)
            byt += (0 if table else 8 * out) + 2 * levels * 12 + 12
    return Cost(float(flops), float(n * byt + fixed))


def oneblob_flops(n: int, dims: int, bins: int, backward: bool = False) -> float:
    """One-blob encoding: per output element a difference, a square, a scale and an exp (4; the
    backward as many again)."""
    return float(n * dims * bins * 4 * (2 if backward else 1))


def orb_bytes(h: int, w: int, levels: int, scale: float) -> float:
    """Least bytes ORB extraction moves: the RGB image read, the grey image written, each pyramid level
    written from the previous one (read) and every level read once more by FAST and the descriptors."""
    area = sum(scale ** (-2 * k) for k in range(levels))
    return float(3 * h * w + h * w + 2 * h * w * (area - 1) + h * w * area)


def floor_ms(cost: Cost, gflops: float, gbs: float) -> tuple[float, str]:
    """The time ``cost`` takes at the peaks, and which floor it is (``flops`` or ``bytes``; ``-`` when
    there is no FLOP count)."""
    t_flops = cost.flops / (gflops * 1e9) * 1e3
    t_bytes = cost.bytes / (gbs * 1e9) * 1e3
    if cost.flops <= 0:
        return t_bytes, "-"
    return max(t_flops, t_bytes), ("flops" if t_flops >= t_bytes else "bytes")


def make_row(name: str, where: str, ms: float, cost: Cost, peaks: dict, note: str) -> dict:
    """One table row: ``peaks[where]`` holds ``gflops`` and ``gbs``."""
    fl, bound = floor_ms(cost, peaks[where]["gflops"], peaks[where]["gbs"])
    return {"component": name, "where": where, "ms": ms, "gflop": cost.flops / 1e9, "mb": cost.bytes / 1e6,
            "floor_ms": fl, "x_floor": ms / fl if fl > 0 else math.inf, "bound": bound, "note": note}


def format_table(rows: list[dict]) -> str:
    """The rows as a plain text table (component | ms | GFLOP | MB | floor ms | x floor | bound), notes
    under it."""
    w = max([len("component")] + [len(r["component"]) + len(r["where"]) + 3 for r in rows])
    head = f"{'component':<{w}} | {'ms':>9} | {'GFLOP':>8} | {'MB':>8} | {'floor ms':>9} | {'x floor':>8} | bound"
    lines = [head, "-" * len(head)]
    for r in rows:
        name = f"{r['component']} [{r['where']}]"
        lines.append(f"{name:<{w}} | {r['ms']:>9.3f} | {r['gflop']:>8.4f} | {r['mb']:>8.2f} | {r['floor_ms']:>9.4f} | "
                     f"{r['x_floor']:>8.1f} | {r['bound']}")
    lines.append("")
    lines += [f"{r['component']}: {r['note']}" for r in rows]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- measuring
def median_ms(fn, reps: int, warmup: int = 1, sync=None) -> float:
    """Median wall time (ms) of ``fn()`` over ``reps`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    if sync:
        sync()
    ts = []
    for _ in range(max(1, reps)):
        t0 = time.perf_counter()
        fn()
        if sync:
            sync()
        ts.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(ts)


def measure_peaks(device, reps: int, sync) -> dict:
    """Matmul GFLOP/s and copy GB/s on ``device`` (medians)."""
    import torch

    a = torch.randn(MATMUL_N, MATMUL_N, device=device)
    b = torch.randn(MATMUL_N, MATMUL_N, device=device)
    c = torch.empty(MATMUL_N, MATMUL_N, device=device)
    mm = median_ms(lambda: torch.mm(a, b, out=c), reps, 2, sync)
    src = torch.rand(COPY_MB * 2 ** 20 // 4, device=device)
    dst = torch.empty_like(src)
    cp = median_ms(lambda: dst.copy_(src), reps, 2, sync)
    return {"gflops": 2.0 * MATMUL_N ** 3 / (mm * 1e-3) / 1e9, "gbs": 2.0 * COPY_MB * 2 ** 20 / (cp * 1e-3) / 1e9,
            "matmul_ms": mm, "copy_ms": cp}


class Counted:
    """Counts FLOPs (FlopCounterMode) and bytes (every aten op's operands and results) of the code run
    inside it; ``cost`` after it."""

    def __enter__(self):
        import torch
        from torch.utils._python_dispatch import TorchDispatchMode
        from torch.utils._pytree import tree_flatten
        from torch.utils.flop_counter import FlopCounterMode

        counted = self

        class _Traffic(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                kwargs = kwargs or {}
                out = func(*args, **kwargs)
                name = func._schema.name
                if func.is_view or name in NO_TRAFFIC:
                    return out
                reads, writes = {}, {}
                for i, a in enumerate(func._schema.arguments):
                    val = args[i] if i < len(args) else kwargs.get(a.name)
                    mutated = a.alias_info is not None and a.alias_info.is_write
                    for t in tree_flatten(val)[0]:
                        if not isinstance(t, torch.Tensor):
                            continue
                        key = (t.data_ptr(), t.numel(), t.dtype)
                        nbytes = t.numel() * t.element_size()
                        if mutated:
                            writes[key] = nbytes
                        if not (mutated and (name in WRITE_ONLY or a.name == "out")):
                            reads[key] = nbytes
                for t in tree_flatten(out)[0]:
                    if isinstance(t, torch.Tensor):
                        writes[(t.data_ptr(), t.numel(), t.dtype)] = t.numel() * t.element_size()
                counted.bytes += sum(reads.values()) + sum(writes.values())
                return out

        self.bytes = 0
        self._flops = FlopCounterMode(display=False)
        self._traffic = _Traffic()
        self._flops.__enter__()
        self._traffic.__enter__()
        return self

    def __exit__(self, *exc):
        self._traffic.__exit__(*exc)
        self._flops.__exit__(*exc)
        self.cost = Cost(float(self._flops.get_total_flops()), float(self.bytes))
        return False


def counted(fn) -> Cost:
    with Counted() as c:
        fn()
    return c.cost


# ---------------------------------------------------------------------------------------------- inputs
def load_frames(n: int):
    """(config, intrinsics, the first ``n`` frames, source): the Bonn clip when present, else a rendered
    synthetic walker scene at 640x480."""
    from dynslam_cli.config.resolve import resolve_config
    from dynslam_cli.data.open import open_sequence

    if BONN.is_dir():
        path, source, tmp = BONN, f"Bonn clip {BONN.name}", None
    else:
        from dynslam_cli.synth.config import SynthConfig
        from dynslam_cli.synth.render import render_preset

        tmp = tempfile.TemporaryDirectory()
        path = Path(tmp.name) / "walker"
        render_preset("walker", path, SynthConfig(width=640, height=480, frames=n, seed=0), progress=False)
        source = "synthetic walker scene (the Bonn clip is absent)"
    cfg = resolve_config(str(path))
    seq = open_sequence(str(path), cfg, progress=False)
    frames = list(itertools.islice(iter(seq), n))
    if tmp is not None:
        tmp.cleanup()
    return cfg, seq.intrinsics, frames, source


def capture_backend_calls(cfg, intr, frames) -> tuple[list, list]:
    """The arguments of every pose-only optimisation and local bundle adjustment the backend runs on
    ``frames`` (no motion mask)."""
    import dynslam_cli.backend.backend as bk
    import dynslam_cli.backend.tracking as trk

    poses, bas = [], []
    real_pose, real_ba = trk.optimize_pose, bk.local_bundle_adjustment

    def pose_spy(*a, **k):
        poses.append((a, k))
        return real_pose(*a, **k)

    def ba_spy(*a, **k):
        bas.append((a, k))
        return real_ba(*a, **k)

    trk.optimize_pose, bk.local_bundle_adjustment = pose_spy, ba_spy
    try:
        be = bk.Backend((intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height), cfg.backend)
        for f in frames:
            be.track(f.index, f.rgb, f.depth_full if f.depth_full is not None else f.depth, stamp=f.timestamp)
    finally:
        trk.optimize_pose, bk.local_bundle_adjustment = real_pose, real_ba
    return poses, bas


def ray_points(slam, cur, n_rays: int):
    """World sample points (n_rays x samples, 3) of ``n_rays`` random valid pixels of ``cur``, sampled
    along the rays as mapping samples them."""
    import torch

    from dynslam_cli.map.render import sample_depths

    s = slam
    idx = torch.from_numpy(s.sample(cur.valid, n_rays)).to(s.device)
    T = s.t(s.poses[cur.idx])
    d = s.dirs[idx] @ T[:3, :3].T
    z = sample_depths(cur.depth[idx], s.cfg.map, s.tgen)
    return (T[:3, 3] + d[:, None, :] * z[..., None]).reshape(-1, 3).contiguous()


# ---------------------------------------------------------------------------------------------- components
def fixed_features(feats, out_dim):
    """A module standing in for the hash grid inside NeuralMap.query: it returns precomputed features,
    so that only the decoders and the one-blob encoding run (and are timed)."""
    import torch

    class FixedFeatures(torch.nn.Module):
        def forward(self, x):
            return feats

    m = FixedFeatures()
    m.out_dim = out_dim
    return m


def grid_rows(slam, cur, reps, peaks, where, sync) -> list[dict]:
    """The hash grid's forward and forward+backward on one mapping and one tracking iteration's points."""
    grid = slam.model.grid
    rows = []
    try:
        for label, n_rays, mapping in (("mapping", slam.cfg.mapping.n_rays, True),
                                       ("tracking", slam.cfg.tracking.n_rays, False)):
            rows += _grid_case(slam, cur, label, n_rays, mapping, reps, peaks, where, sync)
    finally:
        grid.embeddings.requires_grad_(True)
        grid.embeddings.grad = None
    return rows


def _grid_case(slam, cur, label, n_rays, mapping, reps, peaks, where, sync) -> list[dict]:
    import torch

    from dynslam_cli.map import _hashgrid_numba as hn

    grid = slam.model.grid
    L, T, F = grid.embeddings.shape
    numba_path = grid.resolve_impl(torch.zeros(1, 3, device=slam.device)) == "numba"
    x = slam.model.normalize(ray_points(slam, cur, n_rays)).detach()
    n = x.shape[0]
    go = torch.randn(n, grid.out_dim, device=slam.device)
    grid.embeddings.requires_grad_(mapping)  # mapping: the table's gradient; tracking: the points' (frozen map)
    xx = x.clone().requires_grad_(not mapping)
    jac = (not mapping) and numba_path and hn.X_GRAD_PARALLEL == "jacobian"

    def fwd():
        grid(xx)

    def fwd_bwd():
        grid.embeddings.grad = None
        xx.grad = None
        grid(xx).backward(go)

    f_cost = hashgrid_forward_cost(n, L, F, jac=jac)
    b_cost = hashgrid_backward_cost(n, L, F, T, table=mapping, x=not mapping, jac=jac)
    grads = "table gradient" if mapping else "point gradient" + (" from the stored Jacobian" if jac else "")
    impl = "numba" if numba_path else "torch"
    name = f"{label} {n_rays}x{n // n_rays}"
    return [make_row(f"hash grid fwd, {name}", where, median_ms(fwd, reps, 2, sync), f_cost, peaks,
                     f"{impl}, {L} levels x {F} features, table 2^{int(math.log2(T))}: the 8-corner gathers"),
            make_row(f"hash grid fwd+bwd, {name}", where, median_ms(fwd_bwd, reps, 2, sync), f_cost + b_cost, peaks,
                     f"{impl}, {grads}" + ("; the scatter and the zero-filled table gradient" if mapping else ""))]


def decoder_rows(slam, cur, reps, peaks, where, sync) -> list[dict]:
    """The SDF and colour decoders with the one-blob encoding, forward+backward, on one mapping and one
    tracking iteration's points (the grid's features precomputed)."""
    model = slam.model
    real_grid = model.grid
    rows = []
    try:
        for label, n_rays, mapping in (("mapping", slam.cfg.mapping.n_rays, True),
                                       ("tracking", slam.cfg.tracking.n_rays, False)):
            rows.append(_decoder_case(slam, cur, label, n_rays, mapping, reps, peaks, where, sync))
    finally:
        model.grid = real_grid
        slam.set_map_grad(True)
    return rows


def _decoder_case(slam, cur, label, n_rays, mapping, reps, peaks, where, sync) -> dict:
    import torch

    model = slam.model
    real_grid, blob = model.grid, model.blob
    pts = ray_points(slam, cur, n_rays).detach()
    n = pts.shape[0]
    with torch.no_grad():
        feats = real_grid(model.normalize(pts)).detach().requires_grad_(True)
    pts.requires_grad_(not mapping)
    slam.set_map_grad(mapping)
    g_sdf = torch.randn(n, device=slam.device)
    g_rgb = torch.randn(n, 3, device=slam.device)

    def step():
        model.zero_grad(set_to_none=True)
        feats.grad = None
        pts.grad = None
        sdf, rgb, _ = model.query(pts, color=True)
        torch.autograd.backward([sdf, rgb], [g_sdf, g_rgb])

    model.grid = fixed_features(feats, real_grid.out_dim)
    try:
        cost = counted(step) + Cost(oneblob_flops(n, blob.n_dims, blob.n_bins, backward=not mapping), 0.0)
        ms = median_ms(step, reps, 2, sync)
    finally:
        model.grid = real_grid
    grads = "parameter and feature gradients" if mapping else "feature and point gradients (frozen map)"
    return make_row(f"decoders+one-blob fwd+bwd, {label} {n_rays}x{n // n_rays}", where, ms, cost, peaks,
                    f"SDF + colour MLPs (hidden {slam.cfg.map.hidden_dim}), {grads}: thin matmuls and "
                    "elementwise passes")


def mapping_row(slam, cur, reps, peaks, where, sync) -> dict:
    import torch

    mc, mp = slam.cfg.mapping, slam.cfg.map
    iters = 5
    n_rays = mc.n_rays
    grid = slam.model.grid
    L, T, F = grid.embeddings.shape
    cost = counted(lambda: slam.mapper.optimize(cur, 1, n_rays, first=True))
    if grid.resolve_impl(torch.zeros(1, 3, device=slam.device)) == "numba":  # invisible to the op counter
        n = n_rays * (mp.SAMPLES_FREE + mp.samples_surface) + (mp.SMOOTH_GRID ** 3 if mp.W_SMOOTH > 0 else 0)
        cost = cost + hashgrid_forward_cost(n, L, F) + hashgrid_backward_cost(n, L, F, T, table=True, x=False)
    ms = median_ms(lambda: slam.mapper.optimize(cur, iters, n_rays, first=True), max(1, reps // 2), 1, sync) / iters
    return make_row(f"mapping iteration ({n_rays} rays)", where, ms, cost, peaks,
                    "render_rays + ray_losses + backward + fused Adam on every parameter (the whole hash table: "
                    f"{L * T * F * 4 / 1e6:.0f} MB x 7 passes)")


def render_row(slam, reps, peaks, where, sync) -> dict:
    import torch

    from dynslam_cli.slam.render import RENDER_BLOCK, RENDER_COARSE, RENDER_FINE

    scale = min(1.0, slam.cfg.motion.check_width / float(slam.W))
    h, w = max(1, int(round(slam.H * scale))), max(1, int(round(slam.W * scale)))
    pose = slam.poses[0]
    grid = slam.model.grid
    grid_call = grid.forward
    n_pts = [0]  # points the grid encodes (the coarse sweep stops at each ray's first crossing)

    def counting(x):
        n_pts[0] += x.shape[0]
        return grid_call(x)

    grid.forward = counting
    try:
        cost = counted(lambda: slam.render(pose, scale))
    finally:
        del grid.forward
    if grid.resolve_impl(torch.zeros(1, 3, device=slam.device)) == "numba":
        L, _, F = grid.embeddings.shape
        cost = cost + hashgrid_forward_cost(n_pts[0], L, F)
    ms = median_ms(lambda: slam.render(pose, scale), reps, 1, sync)
    return make_row(f"check render {w}x{h}", where, ms, cost, peaks,
                    f"up to {RENDER_COARSE} SDF-only samples per pixel ({RENDER_BLOCK} at a time, to the first "
                    f"crossing; {n_pts[0] / (h * w):.0f} in all with the {RENDER_FINE} coloured), no gradients")


def encoder_row(cfg, frame, threads, reps, peaks, where: str = "cpu", sync=None) -> dict | None:
    """The encoder where a run on ``where`` runs it (cuda: the torch network on the GPU)."""
    import torch

    from dynslam_cli.motion.encode_base import masked_crops, normalise_batch
    from dynslam_cli.motion.encode_effnet import MEAN, STD, EffNetLite0Encoder, build_model
    from dynslam_cli.motion.segmenters import make_segmenter

    seg = make_segmenter(cfg.motion, None, threads).segment(frame.rgb, frame.depth)
    if seg.count == 0:
        return None
    enc = EffNetLite0Encoder.from_config(cfg.motion, threads, where)
    ms = median_ms(lambda: enc.encode(frame.rgb, seg.ids), reps, 1, sync)
    net = build_model(enc.input_size).eval()
    layer_bytes = [0]

    def hook(mod, inp, out):
        layer_bytes[0] += sum(t.numel() * t.element_size() for t in (mod.weight, inp[0], out))

    hooks = [m.register_forward_hook(hook) for m in net.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]
    x = torch.from_numpy(normalise_batch(masked_crops(frame.rgb, seg.ids, enc.input_size, enc.margin, enc.fill),
                                         MEAN, STD))
    with torch.no_grad():
        flops = counted(lambda: net(x)).flops
    for h in hooks:
        h.remove()
    return make_row(f"instance encoder, {seg.count} crops {enc.input_size}px", where, ms,
                    Cost(flops, float(layer_bytes[0])), peaks,
                    f"EfficientNet-Lite0 on {enc.backend} (crops included), geometric segments of the frame; "
                    "depthwise convolutions do little arithmetic per byte")


def backend_rows(cfg, intr, frames, reps, peaks) -> list[dict]:
    from dynslam_cli.backend.features import LEVELS, SCALE, Detector
    from dynslam_cli.backend.tracking import optimize_pose
    from dynslam_cli.data.config import DataConfig

    f = frames[0]
    det = Detector(cfg.backend.features, intr.width, intr.height, DataConfig.DEPTH_NOISE)
    depth = f.depth_full if f.depth_full is not None else f.depth
    rows = [make_row(f"ORB extraction {intr.width}x{intr.height}", "cpu",
                     median_ms(lambda: det.detect(f.rgb, depth), reps, 1),
                     Cost(0.0, orb_bytes(intr.height, intr.width, LEVELS, SCALE)), peaks,
                     f"{cfg.backend.features} keypoints, {LEVELS} levels; bytes floor only (no FLOP model for "
                     "FAST/orientation/BRIEF)")]
    poses, bas = capture_backend_calls(cfg, intr, frames)
    if poses:
        a, k = sorted(poses, key=lambda c: len(c[0][2]))[len(poses) // 2]  # the median-sized call
        n = len(a[2])
        rows.append(make_row(f"pose-only optimisation, {n} matches", "cpu",
                             median_ms(lambda: optimize_pose(*a, **k), reps, 1),
                             Cost(float(POSE_ROUNDS * n * POSE_FLOPS_PER_OBS), float(n * (24 + 16 + 8 + 8) + 256)),
                             peaks, "numpy Gauss-Newton on 6 unknowns: FLOPs a lower bound (one iteration a round); "
                             "per-call numpy overheads dominate"))
    if bas:
        from dynslam_cli.backend.bundle import local_bundle_adjustment

        a, k = bas[-1]
        nbytes = sum(getattr(v, "nbytes", 0) for v in list(a) + list(k.values()))
        nbytes += sum(getattr(v, "nbytes", 0) for v in a[1].values())  # the poses dict
        rows.append(make_row(f"local bundle adjustment, {len(a[2]) + len(a[3])} keyframes, {len(a[4])} landmarks",
                             "cpu", median_ms(lambda: local_bundle_adjustment(*a, **k), max(1, reps // 2), 1),
                             Cost(0.0, float(nbytes)), peaks,
                             "gtsam Levenberg-Marquardt (factors built in Python); bytes floor only"))
    return rows


def run(reps: int, threads: int, device_name: str) -> dict:
    import torch

    from dynslam_cli.slam.system import SLAM
    from dynslam_cli.utils.threads import set_threads

    threads = set_threads(threads)
    device = torch.device(device_name)
    sync = torch.cuda.synchronize if device.type == "cuda" else None
    peaks = {"cpu": measure_peaks(torch.device("cpu"), reps, None)}
    if device.type == "cuda":
        peaks["cuda"] = measure_peaks(device, reps, sync)
    where = device.type
    cfg, intr, frames, source = load_frames(FRAMES)
    torch.manual_seed(0)
    slam = SLAM(cfg, intr, device)
    slam.track(frames[0])
    cur = slam.cur
    rows = grid_rows(slam, cur, reps, peaks, where, sync)
    rows += decoder_rows(slam, cur, reps, peaks, where, sync)
    rows.append(mapping_row(slam, cur, reps, peaks, where, sync))
    rows.append(render_row(slam, reps, peaks, where, sync))
    enc = encoder_row(cfg, frames[0], threads, reps, peaks, where, sync)
    if enc is not None:
        rows.append(enc)
    rows += backend_rows(cfg, intr, frames, reps, peaks)
    return {"threads": threads, "device": str(device), "reps": reps, "source": source,
            "size": [int(intr.width), int(intr.height)], "peaks": peaks, "rows": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=10, help="timed repetitions per component (median)")
    ap.add_argument("--threads", type=int, default=2, help="torch/numba/onnxruntime threads")
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the neural map runs")
    ap.add_argument("--json", default=None, help="also write the table as JSON to this file")
    a = ap.parse_args(argv)
    import torch

    if a.device == "cuda" and not torch.cuda.is_available():
        print("error: --device cuda requested but CUDA is not available", file=sys.stderr)
        return 2
    if a.reps < 1:
        print(f"error: --reps must be at least 1, got {a.reps}", file=sys.stderr)
        return 2
    res = run(a.reps, a.threads, a.device)
    print(f"input: {res['source']}, {res['size'][0]}x{res['size'][1]}; threads {res['threads']}, device "
          f"{res['device']}, median of {res['reps']} reps")
    for k, p in res["peaks"].items():
        print(f"peak {k}: matmul {p['gflops']:.1f} GFLOP/s ({MATMUL_N}^2 fp32), copy {p['gbs']:.1f} GB/s "
              f"({COPY_MB} MB, read + write)")
    print()
    print(format_table(res["rows"]))
    if a.json:
        from dynslam_cli.utils.io import write_json_atomic

        write_json_atomic(a.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
