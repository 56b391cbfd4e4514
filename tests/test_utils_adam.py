"""dynslam_cli.utils.adam: torch.optim.Adam's update without torch.optim."""

from __future__ import annotations

import copy
import subprocess
import sys

import pytest
import torch

from dynslam_cli.utils.adam import Adam


def _problem(seed: int = 0):
    """Two parameters (a 'table' and a small matrix) and a loss with a non-trivial gradient."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(64, 2, generator=g)
    b = torch.randn(3, 5, generator=g)
    x = torch.randn(7, 3, generator=g)
    return a, b, x


def _loss(a, b, x, it: int):
    return ((x @ b).sum(1) ** 2).mean() + (a[it % 64] ** 3).sum() + a.square().mean()


def _run(opt_cls, fused: bool, steps: int = 25, **kw):
    a0, b0, x = _problem()
    a, b = a0.clone().requires_grad_(True), b0.clone().requires_grad_(True)
    opt = opt_cls([a, b], lr=0.01, betas=(0.9, 0.99), eps=1e-15, fused=fused, **kw)
    for it in range(steps):
        opt.zero_grad(set_to_none=True)
        _loss(a, b, x, it).backward()
        opt.step()
    return a.detach(), b.detach(), opt


class TestAdamStep:
    @pytest.mark.parametrize("fused", [True, False])
    def test_bit_identical_to_torch_optim(self, fused):
        a1, b1, _ = _run(Adam, fused)
        a2, b2, _ = _run(torch.optim.Adam, fused)
        assert torch.equal(a1, a2) and torch.equal(b1, b2)

    def test_known_first_step(self):
        # the first Adam step moves every parameter with a non-zero gradient by lr against its sign
        p = torch.tensor([1.0, -2.0, 3.0], requires_grad=True)
        opt = Adam([p], lr=0.1)
        (p * torch.tensor([2.0, -0.5, 0.0])).sum().backward()
        opt.step()
        assert torch.allclose(p.detach(), torch.tensor([0.9, -1.9, 3.0]), atol=1e-6)

    def test_parameter_without_gradient_is_left_alone(self):
        p, q = torch.ones(3, requires_grad=True), torch.ones(2, requires_grad=True)
        opt = Adam([p, q], lr=0.1, fused=True)
        p.sum().backward()
        opt.step()
        assert torch.equal(q.detach(), torch.ones(2)) and not opt.state[1]
        assert float(opt.state[0]["step"]) == 1.0

    def test_zero_grad(self):
        p = torch.ones(3, requires_grad=True)
        opt = Adam([p], lr=0.1)
        p.sum().backward()
        opt.zero_grad(set_to_none=False)
        assert torch.equal(p.grad, torch.zeros(3))
        opt.zero_grad()
        assert p.grad is None

    def test_invalid_arguments(self):
        with pytest.raises(ValueError, match="empty"):
            Adam([], lr=0.1)
        with pytest.raises(ValueError, match="invalid"):
            Adam([torch.ones(1, requires_grad=True)], lr=0.1, betas=(0.9, 1.0))
        with pytest.raises(ValueError, match="fused"):
            Adam([torch.ones(1, dtype=torch.int64)], lr=0.1, fused=True)


class TestAdamStateDict:
    @pytest.mark.parametrize("fused", [True, False])
    def test_round_trip_with_torch_optim(self, fused):
        """A state dict of either loads into the other and the next steps agree bit for bit."""
        a, b, ours = _run(Adam, fused, steps=10)
        _, _, theirs = _run(torch.optim.Adam, fused, steps=10)
        for src, dst_cls in ((ours, torch.optim.Adam), (theirs, Adam)):
            results = []
            for cls, state in ((Adam, ours.state_dict()), (dst_cls, src.state_dict())):
                pa, pb = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
                opt = cls([pa, pb], lr=0.01, betas=(0.9, 0.99), eps=1e-15, fused=fused)
                opt.load_state_dict(copy.deepcopy(state))  # torch.optim's loader shares the tensors
                x = _problem()[2]
                for it in range(10, 15):
                    opt.zero_grad()
                    _loss(pa, pb, x, it).backward()
                    opt.step()
                results.append((pa.detach(), pb.detach()))
            assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])

    def test_wrong_shape_rejected(self):
        _, _, opt = _run(Adam, True, steps=2)
        other = Adam([torch.ones(4, requires_grad=True), torch.ones(3, 5, requires_grad=True)], lr=0.01)
        with pytest.raises(ValueError, match="shape"):
            other.load_state_dict(opt.state_dict())


def test_no_torch_dynamo_import():
    """The reason this module exists: stepping it never imports torch._dynamo (torch.optim does)."""
    code = ("import sys, torch\nfrom dynslam_cli.utils.adam import Adam\n"
            "p = torch.ones(3, requires_grad=True)\nfor fused in (True, False):\n"
            "    o = Adam([p], lr=0.1, fused=fused)\n    p.sum().backward()\n    o.step()\n    o.zero_grad()\n"
            "print('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
