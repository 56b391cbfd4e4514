"""Frame tracking against landmarks (dynslam_cli.backend.tracking): robust pose-only optimisation,
matching by projection, lost when too few matches."""

import numpy as np

from dynslam_cli.backend.features import Keypoints, project
from dynslam_cli.backend.tracking import Camera, optimize_pose, search_by_projection, track_frame

CAM = Camera(300.0, 300.0, 160.0, 120.0, 320, 240, 300.0 * 0.08)


def _pose(rx, ry, t):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xy", [rx, ry]).as_matrix()
    T[:3, 3] = t
    return T


def _scene(n=300, seed=0):
    """World points in front of the camera at ``truth`` and their noisy keypoints."""
    rng = np.random.default_rng(seed)
    truth = _pose(0.05, -0.08, [0.2, -0.1, 0.3])
    uv0, z0 = rng.uniform([20, 20], [300, 220], (n, 2)), rng.uniform(1.5, 4.0, n)  # inside the image
    pc = np.stack([(uv0[:, 0] - CAM.cx) / CAM.fx * z0, (uv0[:, 1] - CAM.cy) / CAM.fy * z0, z0], 1)
    X = pc @ truth[:3, :3].T + truth[:3, 3]
    uv, z = project(truth, X, CAM.K)
    kp = Keypoints(uv + rng.normal(0, 0.5, uv.shape), rng.integers(0, 256, (n, 32), dtype=np.uint8),
                   z * (1 + rng.normal(0, 0.002, n)), np.zeros(n, np.int64), 0.002 * z)
    return truth, X, kp, rng


def _errors(T, truth):
    dR = T[:3, :3].T @ truth[:3, :3]
    ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    return np.linalg.norm(T[:3, 3] - truth[:3, 3]), ang


def test_pose_only_recovers_known_pose_with_30_percent_outliers():
    truth, X, kp, rng = _scene()
    bad = rng.random(len(X)) < 0.3
    kp.uv[bad] = rng.uniform([0, 0], [320, 240], (bad.sum(), 2))  # wrong matches anywhere in the image
    kp.depth[bad[:len(X)] & (rng.random(len(X)) < 0.5)] = 0.0  # some without depth: reprojection only
    start = _pose(0.0, 0.0, [0.25, -0.05, 0.25])  # 8 cm and 5 degrees off
    T, inl = optimize_pose(CAM, start, X, kp, huber=2.8)
    dt, da = _errors(T, truth)
    assert dt < 0.005 and da < 0.1, (dt, da)
    assert (inl & bad).sum() <= 0.05 * bad.sum() and (inl & ~bad).sum() >= 0.95 * (~bad).sum()
    plain, _ = optimize_pose(CAM, start, X, kp, huber=1e6, rounds=1)  # no kernel, no gate: pulled away
    assert _errors(plain, truth)[0] > 5 * dt


def test_search_by_projection_finds_the_right_keypoints():
    truth, X, kp, rng = _scene(200, seed=1)
    des = kp.des.copy()
    des[:, 0] ^= 1  # one bit off: still the nearest descriptor
    perm = rng.permutation(len(X))
    shuffled = kp.subset(perm)
    guess = truth @ _pose(0.0, 0.003, [0.01, 0.0, 0.0])
    lm_rows, kp_rows, vis = search_by_projection(CAM, guess, X, des, np.ones(len(X)), shuffled, radius=15.0)
    assert vis.all() and len(lm_rows) >= 190
    assert np.array_equal(perm[kp_rows], lm_rows)  # each keypoint matched to its own landmark
    assert len(np.unique(kp_rows)) == len(kp_rows)


def test_track_frame_from_a_motion_guess_and_lost_when_too_few():
    truth, X, kp, _ = _scene(250, seed=2)
    ids = np.arange(1000, 1000 + len(X))
    guess = truth @ _pose(0.01, 0.0, [0.03, 0.0, -0.02])
    one = lambda rows, dist: np.ones(len(rows))  # noqa: E731
    tr = track_frame(CAM, guess, kp, ids, X, kp.des, one, 15.0, 2.8, 20, seed=0)
    assert not tr.lost and tr.reason == "motion" and len(tr.lm) >= 240
    assert _errors(tr.pose, truth)[0] < 0.005
    assert np.array_equal(np.sort(tr.lm), np.sort(ids[tr.kp]))
    few = kp.subset(np.arange(12))
    tr = track_frame(CAM, guess, few, ids, X, kp.des, one, 15.0, 2.8, 20, seed=0)
    assert tr.lost and tr.reason.startswith("lost:") and len(tr.lm) == 0
    assert np.array_equal(tr.pose, guess)  # the caller's constant-velocity pose, no jump


def test_track_frame_relocalises_far_from_the_guess():
    truth, X, kp, _ = _scene(250, seed=3)
    ids = np.arange(len(X))
    guess = truth @ _pose(0.0, 0.5, [0.6, 0.0, 0.0])  # far beyond any search radius
    one = lambda rows, dist: np.ones(len(rows))  # noqa: E731
    tr = track_frame(CAM, guess, kp, ids, X, kp.des, one, 15.0, 2.8, 20, seed=0)
    assert not tr.lost and tr.reason == "relocalised"
    assert _errors(tr.pose, truth)[0] < 0.005


class TestInformation:
    def test_known_values(self):
        from dynslam_cli.backend.tracking import information

        info = information(CAM, np.array([2.0, 0.0]), np.array([0.04, 0.0]), np.array([2, 0]))
        assert np.allclose(info[:, :2], [[1.2 ** -4] * 2, [1.0, 1.0]])
        # the disparity bf/d: sigma bf * 0.04 / 2^2 px; no depth, no information
        assert np.isclose(info[0, 2], 1.0 / (CAM.bf * 0.04 / 4.0) ** 2) and info[1, 2] == 0.0

    def test_accurate_depth_is_used_apart_from_noisy_pixels(self):
        """Pixels 2 px noisy, depth 0.1 % accurate: trusting the depth as modelled recovers the pose
        better than treating it as loose (the pixel and the depth noise are independent)."""
        truth, X, kp, rng = _scene(n=200, seed=3)
        kp.uv[:] = project(truth, X, CAM.K)[0] + rng.normal(0, 2.0, kp.uv.shape)
        kp.depth[:] = project(truth, X, CAM.K)[1] * (1 + rng.normal(0, 0.001, len(X)))
        start = _pose(0.0, 0.0, [0.22, -0.08, 0.28])
        errs = {}
        for name, sig in (("modelled", 0.001 * kp.depth), ("loose", 0.1 * kp.depth)):
            kp.dsig[:] = sig
            errs[name] = _errors(optimize_pose(CAM, start, X, kp, huber=2.8)[0], truth)[0]
        assert errs["modelled"] < 0.5 * errs["loose"], errs


class TestPoseCovariance:
    def test_inverse_of_the_numerical_information(self):
        from dynslam_cli.geometry.lie import so3_exp_np as so3_exp
        from dynslam_cli.backend.tracking import information, pose_covariance, stereo_residuals

        truth, X, kp, _ = _scene(80, seed=4)
        kp.depth[::3] = 0.0  # some keypoints without depth: pixels only
        Tcw = np.linalg.inv(truth)
        info = information(CAM, kp.depth, kp.dsig, kp.octave)
        J = np.zeros((len(X), 3, 6))
        eps = 1e-7
        for i in range(6):
            d = np.zeros(6)
            d[i] = eps
            D = np.eye(4)
            D[:3, :3], D[:3, 3] = so3_exp(d[3:]), d[:3]
            _, e1 = stereo_residuals(CAM, D @ Tcw, X, kp.uv, kp.depth)
            _, e0 = stereo_residuals(CAM, Tcw, X, kp.uv, kp.depth)
            J[:, :, i] = -(e1 - e0) / eps  # residual = observed - predicted
        J[kp.depth <= 0, 2, :] = 0
        H = np.einsum("nki,nk,nkj->ij", J, info, J)
        C = pose_covariance(CAM, truth, X, kp)
        assert C.shape == (6, 6) and np.allclose(C, C.T)
        assert np.allclose(C, np.linalg.inv(H), rtol=1e-3, atol=1e-12)

    def test_more_points_fix_the_pose_better(self):
        from dynslam_cli.backend.tracking import pose_covariance

        truth, X, kp, _ = _scene(300, seed=5)
        few = pose_covariance(CAM, truth, X[:30], kp.subset(np.arange(30)))
        many = pose_covariance(CAM, truth, X, kp)
        assert np.trace(many) < 0.2 * np.trace(few)

    def test_too_few_points(self):
        from dynslam_cli.backend.tracking import pose_covariance

        truth, X, kp, _ = _scene(10, seed=6)
        assert np.isinf(pose_covariance(CAM, truth, X[:2], kp.subset(np.arange(2)))).all()


class TestReprojects:
    def test_known_gate_per_octave(self):
        from dynslam_cli.backend.tracking import CHI2_MONO, reprojects

        truth, X, kp, _ = _scene(4, seed=4)
        uv, _ = project(truth, X, CAM.K)
        gate0 = np.sqrt(CHI2_MONO)  # px at octave 0; 1.2^3 times that at octave 3
        off = np.array([0.9 * gate0, 1.1 * gate0, 0.9 * gate0 * 1.2 ** 3, 1.1 * gate0 * 1.2 ** 3])
        k = Keypoints(uv + np.stack([off, np.zeros(4)], 1), kp.des, np.zeros(4), np.array([0, 0, 3, 3]),
                      np.zeros(4))
        assert reprojects(CAM, truth, X, k).tolist() == [True, False, True, False]

    def test_track_frame_reports_every_match_and_the_moved_ones_fail(self):
        truth, X, kp, rng = _scene(250, seed=5)
        ids = np.arange(len(X))
        moved = np.arange(200, 250)  # a thing that started to move: its keypoints are 6 px off
        kp.uv[moved, 0] += 6.0
        one = lambda rows, dist: np.ones(len(rows))  # noqa: E731
        tr = track_frame(CAM, truth, kp, ids, X, kp.des, one, 15.0, 2.8, 20, seed=0)
        assert not tr.lost and len(tr.matched) == len(tr.reprojects) >= 240
        fails = set(tr.matched[~tr.reprojects].tolist())
        assert fails >= set(moved.tolist()) and len(fails - set(moved.tolist())) <= 12


class TestReprojectsWithin:
    def test_part_judged_at_its_own_pose(self):
        from dynslam_cli.backend.tracking import reprojects, reprojects_within

        truth, X, kp, _ = _scene(300, seed=7)
        old = np.arange(300) >= 200  # a third of the landmarks drifted 6 cm from the rest
        X = X.copy()
        X[old] += [0.06, 0.0, 0.0]
        between, _ = optimize_pose(CAM, truth, X, kp, huber=1e6, rounds=1)  # a pose pulled between the two
        part = ~old
        at_pose = reprojects(CAM, between, X, kp)
        within = reprojects_within(CAM, between, X, kp, part, 2.8, 20)
        assert at_pose[part].mean() < 0.7  # judged at the pulled pose, many of the part fail
        assert within[part].mean() > 0.9 and not within[old].any()  # at its own pose they reproject

    def test_too_few_in_the_part_judged_at_the_given_pose(self):
        from dynslam_cli.backend.tracking import reprojects, reprojects_within

        truth, X, kp, _ = _scene(100, seed=8)
        part = np.zeros(100, bool)
        part[:10] = True
        T = truth @ _pose(0.0, 0.0, [0.01, 0.0, 0.0])
        within = reprojects_within(CAM, T, X, kp, part, 2.8, 20)
        assert within[:10].tolist() == reprojects(CAM, T, X[:10], kp.subset(np.arange(10))).tolist()
        assert not within[10:].any()
