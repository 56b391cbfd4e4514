"""Hash grid speed: numba fast path vs the plain-PyTorch reference on CPU.

Prints one row per workload: N points, which gradients, median ms of forward+backward (after
warm-up) for both implementations, the speed-up and the max relative error (max |a-b| / max |b|)
of the values, the x gradient and the table gradient.

    .venv/bin/python benchmarks/bench_hashgrid.py [--reps 10] [--finest 400] [--log2 16] [--threads N]

``--kernels`` also times the alternative parallel layouts of the numba kernels (forward over
points vs over levels vs with the Jacobian stored; x gradient over points vs over levels +
reduction vs the contraction of the stored Jacobian), interleaved.
The machine is shared: the min is printed beside the median as a less noisy figure.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from dynslam_cli.map.hashgrid import HashGrid

# (name, N points, grad wrt x, grad wrt table)
WORKLOADS = [
    ("tracking 1024x16", 1024 * 16, True, False),
    ("mapping 2048x16", 2048 * 16, False, True),
    ("joint/BA 2048x16", 2048 * 16, True, True),
    ("inference 2048x16", 2048 * 16, False, False),
    ("Co-SLAM 1024x43", 1024 * 43, False, True),
]


def rel_err(a, b) -> float:
    if a is None or b is None:
        return float("nan")
    return (a - b).abs().max().item() / max(b.abs().max().item(), 1e-30)


def run_once(grid: HashGrid, x: torch.Tensor, gx: bool, gt: bool, go: torch.Tensor):
    grid.embeddings.requires_grad_(gt)
    grid.embeddings.grad = None
    xx = x.detach().requires_grad_(gx)
    if not (gx or gt):
        with torch.no_grad():
            return grid(xx), None, None
    y = grid(xx)
    y.backward(go)
    return y, xx.grad, grid.embeddings.grad


def time_it(grid, x, gx, gt, go, reps: int, warmup: int = 2):
    """(median ms, min ms) of forward+backward."""
    for _ in range(warmup):
        run_once(grid, x, gx, gt, go)
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        run_once(grid, x, gx, gt, go)
        ts.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(ts), 1e3 * min(ts)


def _layout_fns(grid: HashGrid, n: int) -> dict:
    """The alternative kernel layouts on n random points, as argument-free callables."""
    import numpy as np

    from dynslam_cli.map import _hashgrid_numba as K

    res, dense = K.level_arrays(grid.resolutions, grid.dense)
    table = grid.embeddings.detach().numpy()
    n_lv = table.shape[0]
    x = (torch.rand(n, 3) * 1.02 - 0.01).numpy()
    go = torch.randn(n, grid.out_dim).numpy()
    out = np.empty((n, grid.out_dim), np.float32)
    gx = np.empty((n, 3), np.float32)
    empty = np.empty((0, 0, 0), np.float32)

    def x_levels():
        part = np.empty((n_lv, n, 3), np.float32)
        K.backward_levels(x, table, go, res, dense, False, True, empty, part)
        K.reduce_x(x, part, gx)

    jac = np.empty((n_lv, n, table.shape[2], 3), np.float32)
    K.forward_levels_jac(x, table, res, dense, out, jac)
    return {
        "forward over points": lambda: K.forward_points(x, table, res, dense, out),
        "forward over levels": lambda: K.forward_levels(x, table, res, dense, out),
        "forward+jacobian": lambda: K.forward_levels_jac(x, table, res, dense, out, jac),
        "dx over points": lambda: K.backward_x_points(x, table, go, res, dense, gx),
        "dx over levels+reduce": x_levels,
        "dx from jacobian": lambda: K.contract_jac(x, jac, go, gx),
    }


def kernel_layouts(grid: HashGrid, reps: int) -> None:
    """Interleaved timings of the alternative parallel layouts of the numba kernels."""
    from dynslam_cli.map import _hashgrid_numba as K

    K._sync_threads()
    print("\nkernel layouts (ms, median / min, interleaved):")
    for n in (1024 * 16, 2048 * 16):
        fns = _layout_fns(grid, n)
        ts = {k: [] for k in fns}
        for f in fns.values():
            f()
        for _ in range(reps):
            for k, f in fns.items():
                t0 = time.perf_counter()
                f()
                ts[k].append(1e3 * (time.perf_counter() - t0))
        for k, v in ts.items():
            print(f"  N={n:<6} {k:<24} {statistics.median(v):7.2f} / {min(v):6.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--ref-reps", type=int, default=10, help="repetitions of the (slow) reference")
    ap.add_argument("--finest", type=int, default=400)
    ap.add_argument("--log2", type=int, default=16)
    ap.add_argument("--threads", type=int, default=0, help="torch/numba threads (0 = torch default)")
    ap.add_argument("--kernels", action="store_true", help="also time the alternative kernel layouts")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    grid = HashGrid(n_levels=16, n_features=2, log2_hashmap_size=args.log2, base_resolution=16,
                    finest_resolution=args.finest)
    with torch.no_grad():
        grid.embeddings.uniform_(-1, 1)
    n_dense = sum(grid.dense)
    print(f"hash grid: 16 levels x 2 features, table 2^{args.log2}, resolutions {grid.resolutions[0]}.."
          f"{grid.resolutions[-1]} ({n_dense} dense levels), threads {torch.get_num_threads()}, "
          f"median of {args.reps} (reference {args.ref_reps}) after warm-up")
    hdr = (f"{'workload':<18} {'N':>6} {'grads':<8} {'numba ms':>9} {'(min)':>6} {'torch ms':>9} {'(min)':>6} "
           f"{'speed-up':>8} {'err val':>8} {'err dx':>8} {'err dtab':>8}")
    print(hdr)
    print("-" * len(hdr))
    for name, n, gx, gt in WORKLOADS:
        x = torch.rand(n, 3) * 1.02 - 0.01  # a few points outside [0, 1]
        go = torch.randn(n, grid.out_dim)
        grid.impl = "numba"
        t_fast, m_fast = time_it(grid, x, gx, gt, go, args.reps)
        yf, gxf, gtf = run_once(grid, x, gx, gt, go)
        grid.impl = "torch"
        t_ref, m_ref = time_it(grid, x, gx, gt, go, args.ref_reps, warmup=1)
        yr, gxr, gtr = run_once(grid, x, gx, gt, go)
        grads = "+".join(k for k, on in (("x", gx), ("table", gt)) if on) or "none"
        print(f"{name:<18} {n:>6} {grads:<8} {t_fast:>9.1f} {m_fast:>6.1f} {t_ref:>9.1f} {m_ref:>6.1f} "
              f"{t_ref / t_fast:>7.1f}x {rel_err(yf, yr):>8.1e} {rel_err(gxf, gxr):>8.1e} {rel_err(gtf, gtr):>8.1e}")
    if args.kernels:
        kernel_layouts(grid, args.reps)


if __name__ == "__main__":
    main()
