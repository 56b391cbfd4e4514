"""Local bundle adjustment (dynslam_cli.backend.bundle): lowers a perturbed window's error, keeps
fixed keyframes fixed, flags outlier observations."""

import numpy as np

from dynslam_cli.backend.bundle import local_bundle_adjustment
from dynslam_cli.backend.features import project
from dynslam_cli.backend.tracking import Camera

CAM = Camera(300.0, 300.0, 160.0, 120.0, 320, 240, 300.0 * 0.08)


def _window(n_kf=5, n_pts=150, seed=0):
    """Keyframes moving sideways, points in front of them, each keyframe's stereo observations."""
    rng = np.random.default_rng(seed)
    poses = {}
    for k in range(n_kf):
        T = np.eye(4)
        T[:3, 3] = [0.1 * k, 0.02 * k, 0.0]
        poses[k] = T
    X = np.stack([rng.uniform(-1.0, 1.5, n_pts), rng.uniform(-0.8, 0.8, n_pts), rng.uniform(2.0, 4.0, n_pts)], 1)
    kf, lm, uv, d = [], [], [], []
    for k, T in poses.items():
        p, z = project(T, X, CAM.K)
        ok = (p[:, 0] > 0) & (p[:, 0] < 320) & (p[:, 1] > 0) & (p[:, 1] < 240)
        kf.append(np.full(ok.sum(), k))
        lm.append(np.flatnonzero(ok))
        uv.append(p[ok] + rng.normal(0, 0.2, (ok.sum(), 2)))
        d.append(z[ok])
    obs = [np.concatenate(a) for a in (kf, lm, uv, d)]
    return poses, X, obs, rng


def _perturb(T, rng, s):
    from scipy.spatial.transform import Rotation

    P = np.eye(4)
    P[:3, :3] = Rotation.from_rotvec(rng.normal(0, s, 3)).as_matrix()
    P[:3, 3] = rng.normal(0, s, 3)
    return T @ P


def test_ba_lowers_the_error_and_keeps_fixed_poses_fixed():
    truth, X, (kf, lm, uv, d), rng = _window()
    start = {k: (T.copy() if k < 2 else _perturb(T, rng, 0.03)) for k, T in truth.items()}
    pos0 = X + rng.normal(0, 0.03, X.shape)
    ids = np.arange(len(X))
    bad = rng.random(len(kf)) < 0.05  # 5 % gross outliers
    uv = uv.copy()
    uv[bad] += rng.choice([-1, 1], (bad.sum(), 2)) * rng.uniform(15, 40, (bad.sum(), 2))
    res = local_bundle_adjustment(CAM, start, [2, 3, 4], [0, 1], ids, pos0, kf, lm, uv, d,
                                  np.zeros(len(kf), np.int64), 0.012 * d * d, huber=2.8)
    assert set(res.poses) == {2, 3, 4}  # the fixed keyframes are not returned (not moved)
    assert res.cost < 0.1 * res.cost0
    for k in (2, 3, 4):
        before = np.linalg.norm(start[k][:3, 3] - truth[k][:3, 3])
        after = np.linalg.norm(res.poses[k][:3, 3] - truth[k][:3, 3])
        assert after < 0.004 and after < 0.2 * before, (k, before, after)
    assert np.median(np.linalg.norm(res.pos - X, axis=1)) < 0.4 * np.median(np.linalg.norm(pos0 - X, axis=1))
    assert res.outlier[bad].mean() > 0.9 and res.outlier[~bad].mean() < 0.02


def test_ba_without_fixed_keyframes_holds_the_first_of_the_window():
    truth, X, (kf, lm, uv, d), rng = _window(n_kf=3, seed=1)
    start = {0: truth[0], 1: _perturb(truth[1], rng, 0.01), 2: _perturb(truth[2], rng, 0.01)}
    res = local_bundle_adjustment(CAM, start, [0, 1, 2], [], np.arange(len(X)), X.copy(), kf, lm, uv, d,
                                  np.zeros(len(kf), np.int64), 0.012 * d * d, huber=2.8)
    assert set(res.poses) == {1, 2}
    assert all(np.linalg.norm(res.poses[k][:3, 3] - truth[k][:3, 3]) < 0.004 for k in (1, 2))
