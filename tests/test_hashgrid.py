"""Hash grid: the torch reference against known values and gradcheck, the numba fast path
against the reference (values and both gradients), dispatch and the frozen-table case."""

from __future__ import annotations

import math

import pytest
import torch

from dynslam_cli.errors import DynslamError
from dynslam_cli.map.hashgrid import PRIMES, HashGrid, level_resolutions

numba_kernels = pytest.importorskip("dynslam_cli.map._hashgrid_numba", reason="numba not importable")


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a - b| relative to max |b| (elementwise relative error is meaningless near 0)."""
    scale = b.abs().max().item()
    return (a - b).abs().max().item() / max(scale, 1e-30)


def make_grid(impl="torch", seed=0, **kw) -> HashGrid:
    torch.manual_seed(seed)
    g = HashGrid(impl=impl, **kw)
    with torch.no_grad():  # features of order 1 so that errors are not hidden by the 1e-4 init
        g.embeddings.uniform_(-1.0, 1.0)
    return g


def tricky_points(n: int, seed: int = 1, res=(16, 23, 37)) -> torch.Tensor:
    """Random points, points outside [0, 1], exactly on/next to cell borders and on the faces."""
    gen = torch.Generator().manual_seed(seed)
    x = [torch.rand(n, 3, generator=gen)]
    x.append(torch.rand(n // 4, 3, generator=gen) * 1.6 - 0.3)                    # partly outside
    for r in res:                                                                # on cell borders
        k = torch.randint(0, r + 1, (n // 8, 3), generator=gen).float() / r
        eps = (torch.rand(n // 8, 3, generator=gen) - 0.5) * 2e-6
        x.append(k)
        x.append(k + eps)
    x.append(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.0, 0.5], [-0.5, 2.0, 0.3]]))
    return torch.cat(x).contiguous()


# ---------------------------------------------------------------------------- construction
def test_shapes_dtypes_and_init():
    g = HashGrid(n_levels=4, n_features=2, log2_hashmap_size=10, base_resolution=4, finest_resolution=32)
    assert g.out_dim == 8
    assert g.embeddings.shape == (4, 1024, 2) and g.embeddings.dtype == torch.float32
    assert isinstance(g.embeddings, torch.nn.Parameter)
    assert g.embeddings.abs().max().item() <= 1e-4 and g.embeddings.abs().max().item() > 0
    for impl in ("torch", "numba"):
        g.impl = impl
        y = g(torch.rand(37, 3))
        assert y.shape == (37, 8) and y.dtype == torch.float32
    assert g(torch.rand(0, 3)).shape == (0, 8)


def test_resolutions_and_dense_levels():
    assert level_resolutions(16, 16, 512)[0] == 16 and level_resolutions(16, 16, 512)[-1] == 512
    r = level_resolutions(16, 16, 300)
    b = math.exp((math.log(300) - math.log(16)) / 15)
    assert r == [int(math.floor(16 * b ** lv + 1e-6)) for lv in range(16)]
    assert level_resolutions(1, 8, 8) == [8]
    g = HashGrid(n_levels=16, log2_hashmap_size=16, base_resolution=16, finest_resolution=300)
    assert g.dense == [(x + 1) ** 3 <= 2 ** 16 for x in g.resolutions]
    assert any(g.dense) and not all(g.dense)  # both kinds of level exist in the default setting


def test_bad_arguments_raise():
    with pytest.raises(DynslamError):
        HashGrid(impl="cuda")
    with pytest.raises(DynslamError):
        HashGrid(base_resolution=32, finest_resolution=16)
    g = HashGrid(n_levels=2, log2_hashmap_size=8, base_resolution=4, finest_resolution=8)
    with pytest.raises(DynslamError):
        g(torch.rand(5, 2))
    g.impl = "numba"
    with pytest.raises(DynslamError):
        g(torch.rand(5, 3, dtype=torch.float64))


# ---------------------------------------------------------------------------- known values
@pytest.mark.parametrize("impl", ["torch", "numba"])
def test_linear_table_is_reproduced_on_a_dense_level(impl):
    # one dense level of resolution 8: vertex (i, j, k) sits at x = (i, j, k) / 8.  A table that is a
    # linear function of the vertex position is reproduced exactly by trilinear interpolation.
    g = HashGrid(n_levels=1, n_features=2, log2_hashmap_size=10, base_resolution=8, finest_resolution=8, impl=impl)
    assert g.dense == [True]
    r = 8
    ii, jj, kk = torch.meshgrid(torch.arange(r + 1), torch.arange(r + 1), torch.arange(r + 1), indexing="ij")
    idx = (ii + jj * (r + 1) + kk * (r + 1) ** 2).reshape(-1)
    pos = torch.stack([ii, jj, kk], -1).reshape(-1, 3).float() / r
    with torch.no_grad():
        g.embeddings.zero_()
        g.embeddings[0, idx, 0] = 1.0 + 2.0 * pos[:, 0] - 3.0 * pos[:, 1] + 0.5 * pos[:, 2]
        g.embeddings[0, idx, 1] = pos[:, 2]
    x = torch.rand(200, 3).requires_grad_()
    y = g(x)
    expect0 = 1.0 + 2.0 * x[:, 0] - 3.0 * x[:, 1] + 0.5 * x[:, 2]
    assert torch.allclose(y[:, 0], expect0, atol=1e-5)
    assert torch.allclose(y[:, 1], x[:, 2], atol=1e-6)
    # clamped outside [0, 1]
    out = g(torch.tensor([[1.5, -0.2, 2.0]]))
    assert out[0, 0].item() == pytest.approx(1.0 + 2.0 + 0.5, abs=1e-5)
    assert out[0, 1].item() == pytest.approx(1.0, abs=1e-6)
    # d feature0 / dx = (2, -3, 0.5) everywhere inside
    (gx,) = torch.autograd.grad(y[:, 0].sum(), x)
    assert torch.allclose(gx, torch.tensor([2.0, -3.0, 0.5]).expand_as(gx), atol=1e-4)


@pytest.mark.parametrize("impl", ["torch", "numba"])
@pytest.mark.parametrize("log2, res, v", [(6, 8, (3, 5, 6)),
                                          # products far beyond 32 bits: the numba kernels hash in uint32
                                          (20, 512, (511, 300, 450)), (20, 512, (0, 511, 1))])
def test_hashed_level_reads_the_hashed_vertex(impl, log2, res, v):
    # a level too big for the table: a point exactly on vertex (i, j, k) returns the entry at the hash
    T = 2 ** log2
    g = HashGrid(n_levels=1, n_features=1, log2_hashmap_size=log2, base_resolution=res, finest_resolution=res,
                 impl=impl)
    assert g.dense == [False]
    with torch.no_grad():
        g.embeddings.copy_(torch.arange(T, dtype=torch.float32).view(1, T, 1))
    h = ((v[0] * PRIMES[0]) ^ (v[1] * PRIMES[1]) ^ (v[2] * PRIMES[2])) % T
    y = g(torch.tensor([[v[0] / res, v[1] / res, v[2] / res]]))
    assert y.item() == pytest.approx(float(h), abs=1e-5)


# ---------------------------------------------------------------------------- reference autograd
def test_gradcheck_reference_float64():
    g = HashGrid(n_levels=3, n_features=2, log2_hashmap_size=6, base_resolution=2, finest_resolution=9, impl="auto")
    assert g.dense[0] and not g.dense[-1]
    g = g.double()
    with torch.no_grad():
        g.embeddings.uniform_(-1, 1)
    torch.manual_seed(3)
    x = (torch.rand(6, 3, dtype=torch.float64) * 0.9 + 0.05).requires_grad_()
    assert g.resolve_impl(x) == "torch"  # float64 goes to the reference under auto
    assert torch.autograd.gradcheck(lambda xx, tt: g.forward_torch(xx), (x, g.embeddings), eps=1e-6, atol=1e-6)


# ---------------------------------------------------------------------------- fast path vs reference
@pytest.mark.parametrize("layout", [("levels", "levels"), ("points", "points"), ("levels", "jacobian")])
@pytest.mark.parametrize("cfg", [
    dict(n_levels=16, n_features=2, log2_hashmap_size=12, base_resolution=16, finest_resolution=300),
    dict(n_levels=4, n_features=3, log2_hashmap_size=9, base_resolution=3, finest_resolution=40),
    dict(n_levels=1, n_features=1, log2_hashmap_size=14, base_resolution=16, finest_resolution=16),
])
def test_numba_matches_reference(cfg, layout, monkeypatch):
    monkeypatch.setattr(numba_kernels, "FORWARD_PARALLEL", layout[0])
    monkeypatch.setattr(numba_kernels, "X_GRAD_PARALLEL", layout[1])
    g = make_grid("torch", **cfg)
    assert g.resolve_impl(torch.zeros(1, 3)) == "torch"
    x = tricky_points(600, res=tuple(g.resolutions[:3]))
    xr = x.clone().requires_grad_()
    xn = x.clone().requires_grad_()
    yr = g(xr)
    g.impl = "numba"
    assert g.resolve_impl(xn) == "numba"
    yn = g(xn)
    assert rel_err(yn, yr) < 1e-5
    go = torch.randn_like(yr)
    gxr, gtr = torch.autograd.grad(yr, (xr, g.embeddings), go)
    gxn, gtn = torch.autograd.grad(yn, (xn, g.embeddings), go)
    assert gtr.abs().max() > 0 and gxr.abs().max() > 0
    assert rel_err(gtn, gtr) < 1e-5
    assert rel_err(gxn, gxr) < 1e-5
    outside = ((x < 0) | (x > 1))
    assert outside.any() and (gxn[outside] == 0).all()
    # each gradient alone (separate code paths in the backward)
    (gtab_only,) = torch.autograd.grad(g(x), g.embeddings, go)
    assert rel_err(gtab_only, gtr) < 1e-5
    g.embeddings.requires_grad_(False)
    xo = x.clone().requires_grad_()
    yo = g(xo)
    assert rel_err(yo, yr) < 1e-5
    (gx_only,) = torch.autograd.grad(yo, xo, go)
    assert rel_err(gx_only, gxr) < 1e-5
    assert (gx_only[outside] == 0).all()


def test_numba_gradients_of_a_loss_through_linear_layer():
    # a realistic graph: grid -> linear -> loss, gradients w.r.t. x and the table through .backward()
    g = make_grid("torch", n_levels=6, log2_hashmap_size=10, base_resolution=4, finest_resolution=64)
    lin = torch.nn.Linear(g.out_dim, 1)
    x = tricky_points(300)
    grads = {}
    for impl in ("torch", "numba"):
        g.impl = impl
        g.embeddings.grad = None
        xx = x.clone().requires_grad_()
        (lin(g(xx)) ** 2).mean().backward()
        grads[impl] = (xx.grad.clone(), g.embeddings.grad.clone())
    assert rel_err(grads["numba"][0], grads["torch"][0]) < 1e-5
    assert rel_err(grads["numba"][1], grads["torch"][1]) < 1e-5


@pytest.mark.parametrize("impl", ["torch", "numba"])
def test_nan_input_gives_nan_not_a_crash(impl):
    g = make_grid(impl, n_levels=3, log2_hashmap_size=8, base_resolution=4, finest_resolution=40)
    x = torch.tensor([[float("nan"), 0.5, 0.5], [0.2, 0.3, 0.4]])
    y = g(x)
    assert torch.isnan(y[0]).all() and torch.isfinite(y[1]).all()


def test_auto_dispatch_per_call():
    g = make_grid("auto", n_levels=2, log2_hashmap_size=8, base_resolution=4, finest_resolution=8)
    assert g.resolve_impl(torch.rand(3, 3)) == "numba"
    assert g.resolve_impl(torch.rand(3, 3, dtype=torch.float64)) == "torch"
    g.impl = "torch"
    assert g.resolve_impl(torch.rand(3, 3)) == "torch"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_uses_reference_and_matches_cpu():
    g = make_grid("auto", n_levels=4, log2_hashmap_size=10, base_resolution=4, finest_resolution=64)
    x = tricky_points(200)
    y_cpu = g(x)
    gc = g.cuda()
    assert gc.resolve_impl(x.cuda()) == "torch"
    assert rel_err(gc(x.cuda()).cpu(), y_cpu) < 1e-5


# ---------------------------------------------------------------------------- frozen map (tracking)
def _spy_backward(monkeypatch):
    calls = []
    real = numba_kernels.backward_levels

    def spy(x, table, grad_out, res, dense, do_table, do_x, grad_table, gx_part):
        calls.append((do_table, do_x, grad_table.size, gx_part.size))
        return real(x, table, grad_out, res, dense, do_table, do_x, grad_table, gx_part)

    monkeypatch.setattr(numba_kernels, "backward_levels", spy)
    return calls


@pytest.mark.parametrize("x_parallel", ["levels", "points", "jacobian"])
def test_frozen_table_gets_no_gradient_and_none_is_computed(monkeypatch, x_parallel):
    monkeypatch.setattr(numba_kernels, "X_GRAD_PARALLEL", x_parallel)
    g = make_grid("numba", n_levels=4, log2_hashmap_size=10, base_resolution=4, finest_resolution=64)
    g.embeddings.requires_grad_(False)
    calls = _spy_backward(monkeypatch)
    x = tricky_points(80).requires_grad_()
    g(x).sum().backward()
    assert g.embeddings.grad is None
    if x_parallel == "levels":  # the table gradient is neither computed nor allocated
        assert calls == [(False, True, 0, 4 * x.shape[0] * 3)]
    else:
        assert calls == []
    assert x.grad is not None and x.grad.abs().max() > 0
    # and the reference agrees on the x gradient
    xr = x.detach().clone().requires_grad_()
    g.forward_torch(xr).sum().backward()
    assert rel_err(x.grad, xr.grad) < 1e-5


def test_no_x_gradient_when_x_does_not_require_it(monkeypatch):
    g = make_grid("numba", n_levels=4, log2_hashmap_size=10, base_resolution=4, finest_resolution=64)
    calls = _spy_backward(monkeypatch)
    x = torch.rand(50, 3)
    g(x).sum().backward()
    assert calls == [(True, False, 4 * 1024 * 2, 0)]
    assert g.embeddings.grad is not None and g.embeddings.grad.abs().sum() > 0


def test_non_contiguous_input_and_thread_count():
    g = make_grid("torch", n_levels=4, log2_hashmap_size=10, base_resolution=4, finest_resolution=64)
    big = torch.rand(100, 6)
    x = big[:, ::2]  # non-contiguous view
    assert not x.is_contiguous()
    yr = g(x)
    g.impl = "numba"
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        y1 = g(x)
        assert numba_kernels.numba.get_num_threads() == 1
    finally:
        torch.set_num_threads(old)
    assert rel_err(y1, yr) < 1e-5


def test_tracking_backward_is_a_contraction_of_the_forward_jacobian(monkeypatch):
    # frozen table + x needing a gradient: the forward stores d out / d x, the backward never
    # walks the table again; without autograd (or with a trainable table) no Jacobian is built
    monkeypatch.setattr(numba_kernels, "X_GRAD_PARALLEL", "jacobian")
    g = make_grid("numba", n_levels=5, log2_hashmap_size=9, base_resolution=3, finest_resolution=50)
    jac_calls = []
    real_fwd = numba_kernels.forward_levels_jac

    def spy(*args):
        jac_calls.append(args[-1].shape)
        return real_fwd(*args)

    monkeypatch.setattr(numba_kernels, "forward_levels_jac", spy)
    calls = _spy_backward(monkeypatch)
    x = tricky_points(120, res=tuple(g.resolutions[:3]))
    g(x.clone().requires_grad_()).sum().backward()  # table trainable: the two-gradient pass
    assert jac_calls == [] and len(calls) == 1
    g.embeddings.requires_grad_(False)
    with torch.no_grad():
        g(x.clone().requires_grad_())
    assert jac_calls == []
    xo = x.clone().requires_grad_()
    go = torch.randn(x.shape[0], g.out_dim)
    g(xo).backward(go)
    assert jac_calls == [(5, x.shape[0], 2, 3)] and len(calls) == 1  # no backward_levels call
    xr = x.clone().requires_grad_()
    g.forward_torch(xr).backward(go)
    assert xr.grad.abs().max() > 0 and rel_err(xo.grad, xr.grad) < 1e-5


def test_runs_choose_workqueue_unless_the_user_chose(monkeypatch):
    from dynslam_cli.utils import threads

    monkeypatch.delenv("NUMBA_THREADING_LAYER", raising=False)
    monkeypatch.setattr(numba_kernels.numba.config, "THREADING_LAYER", "default")
    assert threads.choose_numba_layer() == "workqueue"
    assert numba_kernels.numba.config.THREADING_LAYER == "workqueue"
    monkeypatch.setattr(numba_kernels.numba.config, "THREADING_LAYER", "default")
    assert threads.choose_numba_layer() == "workqueue"
    assert numba_kernels.numba.config.THREADING_LAYER == "workqueue"
    monkeypatch.setattr(numba_kernels.numba.config, "THREADING_LAYER", "default")
    monkeypatch.setenv("NUMBA_THREADING_LAYER", "omp")
    assert threads.choose_numba_layer() == "omp"
    assert numba_kernels.numba.config.THREADING_LAYER == "default"  # the user's setting is numba's to read


# ---------------------------------------------------------------------------- determinism
@pytest.mark.parametrize("layout", [("levels", "levels"), ("points", "points"), ("levels", "jacobian")])
def test_numba_values_and_gradients_repeat_bitwise_at_any_thread_count(layout, monkeypatch):
    # many points on a small table (every entry hit from many points, on both threads' shares):
    # the table gradient is summed per level by the one thread that owns the level, in point
    # order, and the x gradient per point in level order, so neither depends on scheduling or on
    # the thread count; the frozen-table case (tracking) takes the x-gradient-only kernels
    monkeypatch.setattr(numba_kernels, "FORWARD_PARALLEL", layout[0])
    monkeypatch.setattr(numba_kernels, "X_GRAD_PARALLEL", layout[1])
    g = make_grid("numba", n_levels=6, log2_hashmap_size=8, base_resolution=4, finest_resolution=200)
    x = tricky_points(20000, res=tuple(g.resolutions[:3]))
    go = torch.randn(x.shape[0], g.out_dim, generator=torch.Generator().manual_seed(5))

    def once(frozen: bool) -> bytes:
        g.embeddings.requires_grad_(not frozen)
        xx = x.clone().requires_grad_()
        y = g(xx)
        grads = torch.autograd.grad(y, (xx,) if frozen else (xx, g.embeddings), go)
        assert all(t.abs().max() > 0 for t in grads)
        return b"".join(t.numpy().tobytes() for t in (y.detach(), *grads))

    old = torch.get_num_threads()
    try:
        for frozen in (False, True):
            got = []
            for n in (2, 2, 1, 2):
                torch.set_num_threads(n)
                got.append(once(frozen))
                assert numba_kernels.numba.get_num_threads() == n
            assert len(set(got)) == 1, (frozen, [hash(b) for b in got])
    finally:
        torch.set_num_threads(old)
        g.embeddings.requires_grad_(True)
