"""Fixed-interval smoothing of a finished trajectory's camera centres (Rauch-Tung-Striebel).

Every tracked camera centre carries white noise (on the Bonn crowd clip 0.3-0.5 cm per axis; its
second differences are 10x the ground truth's).  Online, :mod:`~dynslam_cli.backend.motion` can only
fuse a frame with the frames before it.  Once the sequence is finished every frame can be
estimated from all of them: this is the smoother of the same model, a camera moving under white-noise
acceleration, whose centres were measured with white noise.

- Measurement noise: the white noise the trajectory itself shows (:func:`motion.white_noise`), the
  same for every frame; the first frame is the map's gauge (held).
- Process noise: the acceleration's spectral density ``q`` (m²/s³) that makes the measured centres
  most likely (the forward filter's innovations over a log grid, :data:`Q_GRID`): a camera that
  jerks gets a large ``q`` and little smoothing, a smooth one a small ``q``.
- Robust: a frame whose centre the smoothed track leaves far behind (a wrong pose tracked on movers
  the masks missed, a jump to a relocalised pose) is down-weighted by the Cauchy weight of its
  residual (:data:`CAUCHY` sigma) and the fit repeated until the weights settle (iteratively
  re-weighted least squares, at most :data:`ROUNDS` fits).  The Cauchy influence falls back towards
  zero far out, so a pose centimetres off loses its pull on its neighbours altogether, where a
  Huber weight would only bound it (docs/experiments.md: a two-frame 15 cm excursion kept 14.5 cm
  of it under Huber).

The orientations are left as tracked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dynslam_cli.backend.motion import V0, white_noise

# Spectral densities of the white acceleration tried, m²/s³: from a tripod-steady camera to a thrown one.
Q_GRID = np.logspace(-4, 3, 36)
# Scale of the Cauchy weight 1 / (1 + (res / CAUCHY)^2) on a frame's residual, in measurement sigmas (per axis,
# RMS over the three axes): a frame at CAUCHY sigma counts half.
CAUCHY = 2.0
# Fits at most: the first with every frame weighted alike, then re-weighted by the residuals until no weight
# moves by more than SETTLED.
ROUNDS = 20
SETTLED = 1e-3
# Variance factor of the held first frame (its centre is the map's gauge).
GAUGE = 1e-8
# White noise below this (m, per axis) is none: the track is returned as it is.
NOISE_FLOOR = 1e-6


@dataclass
class Smoothed:
    """``centres`` (N×3): the smoothed camera centres; ``q``: the chosen spectral density (m²/s³;
    nan when nothing was smoothed); ``noise_sd``: the measured white noise per axis (m);
    ``downweighted``: frames the robust fits counted less than half (beyond :data:`CAUCHY` sigma)."""

    centres: np.ndarray
    q: float
    noise_sd: float
    downweighted: int


def smooth_centres(stamps: np.ndarray, centres: np.ndarray) -> Smoothed:
    """Smooth camera centres ``centres`` (N×3, m) observed at ``stamps`` (N, s, increasing); see
    the module's docstring.  Fewer than 8 frames, or no measurable noise (below :data:`NOISE_FLOOR`;
    also where the motion's own accelerations hide it): returned as they are."""
    z = np.asarray(centres, np.float64)
    t = np.asarray(stamps, np.float64)
    r0 = white_noise(z)
    if len(z) < 8 or r0 <= NOISE_FLOOR ** 2:
        return Smoothed(z.copy(), float("nan"), float(np.sqrt(max(r0, 0.0))), 0)
    r = np.full(len(z), r0)
    r[0] = r0 * GAUGE
    q = float("nan")
    out = z
    w = np.ones(len(z))
    for _ in range(ROUNDS):
        nll = _filter(t, z, Q_GRID, r)[-1]
        q = float(Q_GRID[int(np.argmin(nll))])
        out = _rts(t, z, q, r)
        res = np.sqrt(((z - out) ** 2).mean(1) / r0)
        w_new = 1.0 / (1.0 + (res / CAUCHY) ** 2)
        r = r0 / w_new
        r[0] = r0 * GAUGE
        settled = np.abs(w_new - w).max() < SETTLED
        w = w_new
        if settled:
            break
    return Smoothed(out, q, float(np.sqrt(r0)), int((w[1:] < 0.5).sum()))


def _filter(t: np.ndarray, z: np.ndarray, qs: np.ndarray, r: np.ndarray, keep: bool = False):
    """Kalman filter of the constant-velocity model for every spectral density in ``qs`` at once
    (the axes share the covariance).  Returns (history, negative log likelihood of the innovations
    per q); the history, kept only when ``keep``, holds per frame the predicted position, velocity
    and covariance ``a, b, c`` ([[a, b], [b, c]]), then the same filtered."""
    nq = len(qs)
    x0 = np.repeat(z[0][None], nq, 0)  # position per q, axis
    x1 = np.zeros((nq, 3))  # velocity
    a, b, c = np.full(nq, r[0]), np.zeros(nq), np.full(nq, V0 ** 2)  # covariance [[a, b], [b, c]]
    nll = np.zeros(nq)
    hist = []
    if keep:
        hist.append((x0.copy(), x1.copy(), a.copy(), b.copy(), c.copy(), x0.copy(), x1.copy(), a.copy(), b.copy(), c.copy()))
    for i in range(1, len(z)):
        dt = max(float(t[i] - t[i - 1]), 1e-4)
        p0, p1 = x0 + dt * x1, x1
        pa = a + 2 * dt * b + dt * dt * c + qs * dt ** 3 / 3
        pb = b + dt * c + qs * dt ** 2 / 2
        pc = c + qs * dt
        s = pa + r[i]
        k0, k1 = pa / s, pb / s
        inn = z[i][None] - p0
        nll += 0.5 * (3 * np.log(2 * np.pi * s) + (inn * inn).sum(1) / s)
        x0, x1 = p0 + k0[:, None] * inn, p1 + k1[:, None] * inn
        a, b, c = pa - k0 * pa, pb - k0 * pb, pc - k1 * pb
        if keep:
            hist.append((p0, p1, pa, pb, pc, x0, x1, a, b, c))
    return hist, nll


def _rts(t: np.ndarray, z: np.ndarray, q: float, r: np.ndarray) -> np.ndarray:
    """The smoothed positions (N×3) of the model with spectral density ``q``."""
    hist, _ = _filter(t, z, np.array([q]), r, keep=True)
    n = len(z)
    s0, s1 = hist[-1][5][0].copy(), hist[-1][6][0].copy()
    out = np.empty((n, 3))
    out[-1] = s0
    for i in range(n - 2, -1, -1):
        _, _, _, _, _, f0, f1, fa, fb, fc = hist[i]
        p0, p1, pa, pb, pc = (h[0] for h in hist[i + 1][:5])
        dt = max(float(t[i + 1] - t[i]), 1e-4)
        # C = P_f F^T P_p^-1 with P_f = [[fa, fb], [fb, fc]], F = [[1, dt], [0, 1]]
        m00, m01 = fa[0] + dt * fb[0], fb[0]  # P_f F^T, first row
        m10, m11 = fb[0] + dt * fc[0], fc[0]  # second row
        det = pa * pc - pb * pb
        i00, i01, i11 = pc / det, -pb / det, pa / det
        c00, c01 = m00 * i00 + m01 * i01, m00 * i01 + m01 * i11
        c10, c11 = m10 * i00 + m11 * i01, m10 * i01 + m11 * i11
        d0, d1 = s0 - p0, s1 - p1
        s0, s1 = f0[0] + c00 * d0 + c01 * d1, f1[0] + c10 * d0 + c11 * d1
        out[i] = s0
    return out


def smooth_poses(stamps: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, Smoothed]:
    """Camera-to-world poses (N×4×4) with their centres smoothed (:func:`smooth_centres`) and
    their orientations as they were; and the smoother's report."""
    poses = np.asarray(poses, np.float64)
    sm = smooth_centres(stamps, poses[:, :3, 3])
    out = poses.copy()
    out[:, :3, 3] = sm.centres
    return out, sm
