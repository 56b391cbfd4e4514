"""The camera's motion model: a constant-velocity Kalman filter on its pose.

A real camera moves smoothly at 15-30 Hz, but a pose tracked from one frame's keypoints carries
white noise: on the Bonn crowd clip the second differences of the tracked camera centres are 10x
those of the ground truth, with a lag-1 correlation of -0.5 to -0.7 (-2/3 is pure white noise).
The filter fuses each frame's tracked pose (the measurement, with its covariance) with the pose the
motion predicts (the prior: the velocity so far, under white-noise acceleration), so a frame whose
static keypoints pin the pose down weakly in some direction leans on the motion there.

- State: the camera centre and orientation (world frame; the orientation as a rotation matrix with
  a 3-vector error), the linear and angular velocity, and their 12x12 covariance.
- Prediction: constant velocity over the time between the frames, from the last frame's pose as
  the backend holds it now (bundle adjustment may have moved it).  Process noise: white
  acceleration of :data:`ACCEL` m/s² and :data:`ANG_ACCEL` rad/s² (standard deviations), generous
  on purpose: a model fitted to the recent motion (tried) turns stiff while the camera moves
  smoothly and then lags behind its next jerk.
- Measurement: the pose-only optimisation's pose and its covariance, the inverse of its
  Gauss-Newton information, scaled up to the white noise the tracked poses actually show
  (:func:`white_noise`, over the last :data:`WINDOW` frames; never scaled down).
- An innovation beyond the chi-square gate (:data:`GATE`) means the motion model failed (a jerk,
  a relocalisation): the measurement is taken as it is and the velocity is learnt afresh.
"""

from __future__ import annotations

from collections import deque
from typing import Optional

import numpy as np

from dynslam_cli.geometry.lie import so3_exp_np, so3_log_np

# White-noise acceleration (standard deviation) the motion model allows, m/s² and rad/s²: generous for a hand-held or
# robot camera (the Bonn crowd clip's ground truth: 0.3 m/s², about 2 rad/s² with the motion capture's noise;
# synthetic scenes: 0.3-2 m/s², 0.3-2.5 rad/s²).
ACCEL = 2.0
ANG_ACCEL = 3.0
# Raw tracked poses kept to measure their white noise.
WINDOW = 30
# 99.9 % chi-square gate of a 6-dof innovation.
GATE = 22.46
# Velocity standard deviation before anything is known (m/s, rad/s).
V0, W0 = 1.0, 1.0
# Frame interval assumed when a frame has no timestamp (s).
DT_DEFAULT = 1.0 / 30.0


def world_covariance(cov_cam: np.ndarray, T_c2w: np.ndarray) -> np.ndarray:
    """Covariance (6x6) of a pose's camera centre and orientation error in the world frame, from
    the covariance of the left perturbation (translation, rotation) of its world-to-camera
    transform, as :func:`~dynslam_cli.backend.tracking.optimize_pose` parametrises it (the centre
    moves by -R_wc·rho, the orientation by -R_wc·phi)."""
    R = np.asarray(T_c2w, np.float64)[:3, :3]
    B = np.zeros((6, 6))
    B[:3, :3] = -R
    B[3:, 3:] = -R
    return B @ cov_cam @ B.T


def white_noise(x: np.ndarray) -> float:
    """Variance of the white noise on a smooth track ``x`` (N×k, samples at a steady rate), from
    the autocovariance of its second differences: a white-noise-acceleration track with
    measurement noise r has var = q/2 + 6r and lag-1 covariance q/4 - 4r per axis, so
    r = (var - 2·lag1) / 14.  Robust (median-based) estimates, pooled over the k axes; 0 when it
    cannot be told (fewer than 8 samples)."""
    x = np.asarray(x, np.float64)
    if len(x) < 8:
        return 0.0
    s = x[2:] - 2 * x[1:-1] + x[:-2]

    def rvar(a):
        return float(((1.4826 * np.median(np.abs(a - np.median(a, 0)), 0)) ** 2).mean())

    var = rvar(s)
    lag1 = (rvar(s[1:] + s[:-1]) - rvar(s[1:] - s[:-1])) / 4
    return max((var - 2 * lag1) / 14, 0.0)


class MotionFilter:
    """Constant-velocity Kalman filter on the camera pose (see the module's docstring).  Per frame:
    :meth:`predict` (the guess tracking starts from), then :meth:`update` with the tracked pose
    (again, from the same prediction, when the frame is re-tracked) or nothing (a lost frame)."""

    def __init__(self, accel: float = ACCEL, ang_accel: float = ANG_ACCEL):
        self.accel, self.ang_accel = float(accel), float(ang_accel)
        self._unknown_velocity()
        self.stamp: Optional[float] = None
        self.raw: deque = deque(maxlen=WINDOW)  # (centre, rotation vector, centre variance, rotation variance)
        self._prior: Optional[tuple] = None  # (pose, P, v, w) predicted for the frame being tracked
        self._measured = False  # the frame being tracked has its pose in ``raw``

    # -- per frame ------------------------------------------------------------------------------
    def predict(self, last_pose: np.ndarray, stamp: Optional[float]) -> np.ndarray:
        """The pose (4x4 camera-to-world) the motion predicts at ``stamp`` (s; None = one
        :data:`DT_DEFAULT` after the last) from the last frame's ``last_pose``."""
        dt = DT_DEFAULT if stamp is None or self.stamp is None else float(stamp) - self.stamp
        if not np.isfinite(dt) or dt <= 0:
            dt = DT_DEFAULT
        last = np.asarray(last_pose, np.float64)
        pose = np.eye(4)
        pose[:3, 3] = last[:3, 3] + self.v * dt
        pose[:3, :3] = so3_exp_np(self.w * dt) @ last[:3, :3]
        F = np.eye(12)
        F[0:3, 6:9] = dt * np.eye(3)
        F[3:6, 9:12] = dt * np.eye(3)
        Q = np.zeros((12, 12))
        for i, j, s in ((0, 6, self.accel), (3, 9, self.ang_accel)):
            Q[i:i + 3, i:i + 3] = s ** 2 * dt ** 4 / 4 * np.eye(3)
            Q[i:i + 3, j:j + 3] = Q[j:j + 3, i:i + 3] = s ** 2 * dt ** 3 / 2 * np.eye(3)
            Q[j:j + 3, j:j + 3] = s ** 2 * dt ** 2 * np.eye(3)
        P = F @ self.P @ F.T + Q
        self._prior = (pose, P, self.v.copy(), self.w.copy())
        self._measured = False
        self.P = P
        if stamp is not None:
            self.stamp = float(stamp)
        elif self.stamp is not None:
            self.stamp += dt
        return pose.copy()

    def update(self, pose: np.ndarray, cov_cam: np.ndarray, redo: bool = False) -> np.ndarray:
        """Fuse the tracked ``pose`` (4x4 camera-to-world) with the prediction; ``cov_cam``: its
        covariance as :func:`world_covariance` takes it.  ``redo``: the frame was tracked again,
        the earlier update of this frame is replaced.  Returns the fused pose."""
        if self._prior is None or not np.all(np.isfinite(cov_cam)):  # nothing to fuse with
            return np.asarray(pose, np.float64).copy()
        prior, P, v, w = self._prior
        meas = np.asarray(pose, np.float64)
        C = world_covariance(cov_cam, meas)
        if redo and self._measured:
            self.raw.pop()
        self._measured = True
        self.raw.append((meas[:3, 3].copy(), so3_log_np(meas[:3, :3]), float(np.trace(C[:3, :3])) / 3,
                         float(np.trace(C[3:, 3:])) / 3))
        C = self._calibrated(C)
        y = np.concatenate([meas[:3, 3] - prior[:3, 3], so3_log_np(meas[:3, :3] @ prior[:3, :3].T)])
        S = P[:6, :6] + C
        try:
            nis = float(y @ np.linalg.solve(S, y))
        except np.linalg.LinAlgError:
            nis = np.inf
        if not np.isfinite(nis) or nis > GATE:
            # the motion model failed here: the measurement as it is, the velocity learnt afresh
            self._unknown_velocity()
            self.P[:6, :6] = C
            return meas.copy()
        K = P[:, :6] @ np.linalg.inv(S)
        dx = K @ y
        out = np.eye(4)
        out[:3, 3] = prior[:3, 3] + dx[:3]
        out[:3, :3] = so3_exp_np(dx[3:6]) @ prior[:3, :3]
        self.v, self.w = v + dx[6:9], w + dx[9:12]
        IKH = np.eye(12)
        IKH[:, :6] -= K
        self.P = IKH @ P @ IKH.T + K @ C @ K.T  # Joseph form
        return out

    def restart(self, stamp: Optional[float] = None) -> None:
        """The motion is unknown from here (the first frame, a relocalisation, a new map after a
        long loss): zero velocity, wide covariance, no noise history; ``stamp``: the time of the
        frame it restarts at (None = keep the last)."""
        if stamp is not None:
            self.stamp = float(stamp)
        self._unknown_velocity()
        self.raw.clear()
        self._prior = None
        self._measured = False

    def _unknown_velocity(self) -> None:
        """Zero velocity of standard deviation V0 / W0; the pose itself exact."""
        self.v, self.w = np.zeros(3), np.zeros(3)
        self.P = np.diag([0.0] * 6 + [V0 ** 2] * 3 + [W0 ** 2] * 3)

    # -- the tracked poses' white noise --------------------------------------------------------
    def _calibrated(self, C: np.ndarray) -> np.ndarray:
        """``C`` scaled, per block (centre, orientation), up to the white noise of the last
        :data:`WINDOW` tracked poses over its median formal variance (never down)."""
        if len(self.raw) < 8:
            return C
        c = np.array([r[0] for r in self.raw])
        phi = np.array([r[1] for r in self.raw])
        # orientations as small rotations from the newest one: a smooth track near zero
        ref = so3_exp_np(phi[-1]).T
        rel = np.array([so3_log_np(so3_exp_np(p) @ ref) for p in phi])
        g = np.ones(6)
        for blk, track, col in ((slice(0, 3), c, 2), (slice(3, 6), rel, 3)):
            formal = float(np.median([r[col] for r in self.raw]))
            if formal > 0:
                g[blk] = np.sqrt(max(1.0, white_noise(track) / formal))
        return C * g[:, None] * g[None, :]

    # -- checkpoints ---------------------------------------------------------------------------
    def state_dict(self) -> dict:
        raw = np.array([np.concatenate([r[0], r[1], [r[2], r[3]]]) for r in self.raw]).reshape(-1, 8)
        return {"v": self.v.copy(), "w": self.w.copy(), "P": self.P.copy(), "raw": raw,
                "stamp": np.array(np.nan if self.stamp is None else self.stamp)}

    def load_state_dict(self, d: dict) -> None:
        self.v, self.w, self.P = (np.array(d[k], np.float64) for k in ("v", "w", "P"))
        st = float(d["stamp"])
        self.stamp = None if np.isnan(st) else st
        self.raw = deque(((r[:3].copy(), r[3:6].copy(), float(r[6]), float(r[7])) for r in np.asarray(d["raw"])),
                         maxlen=WINDOW)
        self._prior = None
        self._measured = False
