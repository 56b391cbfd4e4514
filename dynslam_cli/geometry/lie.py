"""SE(3) / so(3) exponential and logarithm maps (torch, batched, differentiable; numpy wrappers).

Twist convention: ``xi = (rho, phi)`` with translation part ``rho`` first and rotation vector
``phi`` last; ``exp(xi) = [[R, V rho], [0, 1]]`` with ``R = exp(phi^)`` and ``V`` the left Jacobian
of SO(3).  Small angles use Taylor expansions so values and gradients stay finite at 0.
"""

from __future__ import annotations

import numpy as np
import torch

_SMALL = 1e-4  # below this angle (rad) the series expansions are used


def hat(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) skew-symmetric matrices."""
    z = torch.zeros_like(w[..., 0])
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    return torch.stack([z, -wz, wy, wz, z, -wx, -wy, wx, z], dim=-1).reshape(*w.shape[:-1], 3, 3)


def vee(m: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) skew-symmetric -> (..., 3)."""
    return torch.stack([m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]], dim=-1)


def _coeffs(theta2: torch.Tensor):
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3 with safe small-angle series."""
    small = theta2 < _SMALL * _SMALL
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    a = torch.where(small, 1 - theta2 / 6 + theta2 * theta2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2 * theta2 / 720, (1 - torch.cos(t)) / t2)
    c = torch.where(small, 1.0 / 6 - theta2 / 120 + theta2 * theta2 / 5040, (t - torch.sin(t)) / (t2 * t))
    return a, b, c


def so3_exp(phi: torch.Tensor) -> torch.Tensor:
    """Rodrigues: (..., 3) rotation vectors -> (..., 3, 3) rotations."""
    theta2 = (phi * phi).sum(-1)
    a, b, _ = _coeffs(theta2)
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand(k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def so3_log(r: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations -> (..., 3) rotation vectors (angle in [0, pi])."""
    cos = ((r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2] - 1) / 2).clamp(-1.0, 1.0)
    w = vee(r - r.transpose(-1, -2)) / 2  # sin(theta) * axis
    theta = torch.atan2(torch.linalg.norm(w, dim=-1), cos)  # accurate at small and large angles
    small = theta < 1e-4
    near_pi = theta > np.pi - 1e-3
    sin = torch.sin(theta)
    scale = torch.where(small, 1 + theta * theta / 6, theta / torch.where(small, torch.ones_like(sin), sin))
    out = w * scale[..., None]
    if bool(near_pi.any()):
        # axis from the diagonal of (R + I) / 2 = a a^T (theta = pi)
        m = (r + torch.eye(3, dtype=r.dtype, device=r.device)) / 2
        diag = torch.diagonal(m, dim1=-2, dim2=-1).clamp_min(0)
        i = diag.argmax(-1, keepdim=True)
        col = torch.gather(m, -1, i[..., None, :].expand(*m.shape[:-1], 1)).squeeze(-1)
        axis = col / torch.sqrt(torch.gather(diag, -1, i)).clamp_min(1e-12)
        # fix sign with the antisymmetric part (when available)
        sgn = torch.sign((axis * w).sum(-1, keepdim=True))
        sgn = torch.where(sgn == 0, torch.ones_like(sgn), sgn)
        out = torch.where(near_pi[..., None], axis * sgn * theta[..., None], out)
    return out


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """(..., 6) twists (rho, phi) -> (..., 4, 4) rigid transforms."""
    rho, phi = xi[..., :3], xi[..., 3:]
    theta2 = (phi * phi).sum(-1)
    a, b, c = _coeffs(theta2)
    k = hat(phi)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand(k.shape)
    rot = eye + a[..., None, None] * k + b[..., None, None] * k2
    v = eye + b[..., None, None] * k + c[..., None, None] * k2
    t = (v @ rho[..., None])[..., 0]
    top = torch.cat([rot, t[..., None]], dim=-1)
    bottom = torch.zeros(*xi.shape[:-1], 1, 4, dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) rigid transforms -> (..., 6) twists (rho, phi)."""
    rot, t = T[..., :3, :3], T[..., :3, 3]
    phi = so3_log(rot)
    theta2 = (phi * phi).sum(-1)
    a, b, _ = _coeffs(theta2)
    k = hat(phi)
    eye = torch.eye(3, dtype=T.dtype, device=T.device).expand(k.shape)
    # V^-1 = I - K/2 + (1 - A / (2B)) / theta^2 K^2
    small = theta2 < _SMALL * _SMALL
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    d = torch.where(small, 1.0 / 12 + theta2 / 720, (1 - a / (2 * b)) / safe2)
    vinv = eye - 0.5 * k + d[..., None, None] * (k @ k)
    rho = (vinv @ t[..., None])[..., 0]
    return torch.cat([rho, phi], dim=-1)


def se3_inv(T: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 4, 4) rigid transforms."""
    rt = T[..., :3, :3].transpose(-1, -2)
    t = -(rt @ T[..., :3, 3:4])
    out = torch.zeros_like(T)
    out[..., :3, :3] = rt
    out[..., :3, 3:4] = t
    out[..., 3, 3] = 1
    return out


def se3_exp_np(xi) -> np.ndarray:
    return se3_exp(torch.as_tensor(np.asarray(xi, dtype=np.float64))).numpy()


def se3_log_np(T) -> np.ndarray:
    return se3_log(torch.as_tensor(np.asarray(T, dtype=np.float64))).numpy()


def so3_exp_np(phi) -> np.ndarray:
    """Rotation matrix of the rotation vector ``phi`` (numpy, Rodrigues)."""
    th = float(np.linalg.norm(phi))
    if th < 1e-12:
        return np.eye(3)
    k = np.asarray(phi, np.float64) / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx


def so3_log_np(R: np.ndarray) -> np.ndarray:
    """Rotation vector of the rotation matrix ``R`` (numpy; a half turn's axis from the symmetric part)."""
    c = float(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))
    th = float(np.arccos(c))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-9:
        return 0.5 * w
    if np.pi - th < 1e-6:  # half turn: the axis from the symmetric part
        a = np.sqrt(np.maximum((np.diag(R) + 1) / 2, 0))
        i = int(np.argmax(a))
        col = (R[:, i] + np.eye(3)[:, i]) / 2
        return th * col / np.linalg.norm(col)
    return th / (2 * np.sin(th)) * w


def inv_np(T: np.ndarray) -> np.ndarray:
    """Inverse of a (..., 4, 4) rigid transform (numpy)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ T[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1
    return out


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Project the rotation block of a 4x4 onto SO(3) (SVD), keeping the translation."""
    T = np.array(T, dtype=np.float64)
    u, _, vt = np.linalg.svd(T[:3, :3])
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    T[:3, :3] = r
    T[3] = [0, 0, 0, 1]
    return T
