import numpy as np
import torch

from dynslam_cli.geometry.lie import (inv_np, se3_exp, se3_exp_np, se3_log, se3_log_np, so3_exp, so3_exp_np, so3_log,
                                      so3_log_np)


def test_se3_exp_log_round_trip_random_and_small():
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(50, 6)) * np.array([0.5, 0.5, 0.5, 1.0, 1.0, 1.0])
    xi[:10, 3:] *= 1e-7  # tiny angles use the series
    xi[10:12] = 0.0
    ang = np.linalg.norm(xi[:, 3:], axis=1, keepdims=True)
    xi[:, 3:] *= np.minimum(1.0, 3.0 / np.maximum(ang, 1e-30))  # angles below pi (log's range)
    back = se3_log_np(se3_exp_np(xi))
    assert np.allclose(back, xi, atol=1e-9)


def test_exp_is_a_rigid_transform_and_log_near_pi():
    phi = torch.tensor([[0.0, 0.0, np.pi - 1e-5], [np.pi - 1e-4, 0, 0]], dtype=torch.float64)
    R = so3_exp(phi)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand(2, 3, 3), atol=1e-12)
    assert torch.allclose(so3_log(R), phi, atol=1e-6)
    T = se3_exp_np(np.array([0.1, -0.2, 0.3, 0.2, 0.1, -0.3]))
    assert np.allclose(T @ inv_np(T), np.eye(4), atol=1e-12)


def test_se3_exp_gradient_matches_finite_differences_at_zero_and_away():
    for x0 in (torch.zeros(6, dtype=torch.float64), torch.tensor([0.1, 0.2, -0.1, 0.3, -0.2, 0.1], dtype=torch.float64)):
        x = x0.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(lambda v: se3_exp(v), (x,), eps=1e-6, atol=1e-6)
    # exp(xi) ~ I + xi^ at first order: derivative of translation wrt rho is identity at 0
    x = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    jac = torch.autograd.functional.jacobian(lambda v: se3_exp(v)[:3, 3], x)
    assert torch.allclose(jac[:, :3], torch.eye(3, dtype=torch.float64))
    assert torch.isfinite(se3_log(se3_exp(x)).sum())


class TestSo3Numpy:
    def test_agrees_with_the_torch_maps(self):
        phi = np.array([0.3, -1.1, 0.5])
        R = so3_exp(torch.as_tensor(phi)).numpy()
        assert np.allclose(so3_exp_np(phi), R, atol=1e-12) and np.allclose(so3_log_np(R), phi, atol=1e-10)

    def test_round_trip(self):
        rng = np.random.default_rng(0)
        for phi in [np.zeros(3), np.array([1e-10, 0, 0]), *rng.normal(0, 1.0, (20, 3)), np.array([0, 0, np.pi - 1e-8])]:
            R = so3_exp_np(phi)
            assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1)
            assert np.allclose(so3_exp_np(so3_log_np(R)), R, atol=1e-7)

    def test_known_values(self):
        assert np.allclose(so3_exp_np(np.array([0, 0, np.pi / 2])), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
        assert np.allclose(so3_log_np(np.diag([1.0, -1.0, -1.0])), [np.pi, 0, 0], atol=1e-6)  # half turn
