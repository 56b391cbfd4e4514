"""The camera's motion model (dynslam_cli.backend.motion): the covariance's change of frame, the
white noise of a tracked track, and the constant-velocity Kalman filter."""

import numpy as np
import pytest

from dynslam_cli.backend.motion import DT_DEFAULT, GATE, MotionFilter, white_noise, world_covariance
from dynslam_cli.geometry.lie import so3_exp_np as so3_exp
from dynslam_cli.geometry.lie import so3_log_np as so3_log


def _pose(c, phi=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = so3_exp(np.asarray(phi, float))
    T[:3, 3] = c
    return T


class TestWorldCovariance:
    def test_identity_orientation_keeps_the_covariance(self):
        A = np.random.default_rng(1).normal(size=(6, 6))
        C = A @ A.T
        assert np.allclose(world_covariance(C, np.eye(4)), C)

    def test_matches_a_numerical_change_of_frame(self):
        """Perturb the world-to-camera transform on the left and read the centre and orientation
        change in the world frame: the Jacobian world_covariance uses."""
        T = _pose([0.3, -0.2, 1.0], [0.2, -0.4, 0.7])
        Tcw = np.linalg.inv(T)
        J = np.zeros((6, 6))
        eps = 1e-6
        for i in range(6):
            d = np.zeros(6)
            d[i] = eps
            D = np.eye(4)
            D[:3, :3] = so3_exp(d[3:])
            D[:3, 3] = d[:3]
            T2 = np.linalg.inv(D @ Tcw)
            J[:3, i] = (T2[:3, 3] - T[:3, 3]) / eps
            J[3:, i] = so3_log(T2[:3, :3] @ T[:3, :3].T) / eps
        C = np.diag([1.0, 2, 3, 4, 5, 6])
        assert np.allclose(world_covariance(C, T), J @ C @ J.T, rtol=1e-4, atol=1e-6)


class TestWhiteNoise:
    def test_recovers_the_noise_of_a_smooth_track(self):
        rng = np.random.default_rng(2)
        t = np.arange(400) / 30.0
        smooth = np.stack([0.3 * t, 0.1 * np.sin(t), 0.05 * t ** 2], 1)
        r = white_noise(smooth + rng.normal(0, 0.005, smooth.shape))
        assert 0.7 * 0.005 ** 2 < r < 1.4 * 0.005 ** 2, np.sqrt(r)

    def test_a_smooth_track_has_none(self):
        t = np.arange(60) / 30.0
        assert white_noise(np.stack([t, t ** 2, np.sin(t)], 1)) < 1e-10

    def test_too_short(self):
        assert white_noise(np.zeros((5, 3))) == 0.0


class TestMotionFilter:
    def _run(self, n=60, noise=0.005, seed=3, cov=None):
        """A camera at constant velocity (0.3 m/s, 0.2 rad/s), measured with white noise."""
        rng = np.random.default_rng(seed)
        mf = MotionFilter()
        cov = np.diag([noise ** 2] * 3 + [(noise / 2) ** 2] * 3) if cov is None else cov
        truth, meas, fused = [], [], []
        last = _pose([0, 0, 0])
        mf.restart(0.0)
        for k in range(1, n):
            t = k * DT_DEFAULT
            T = _pose([0.3 * t, 0, 0], [0, 0.2 * t, 0])
            M = _pose(T[:3, 3] + rng.normal(0, noise, 3), so3_log(T[:3, :3]) + rng.normal(0, noise / 2, 3))
            mf.predict(last, t)
            F = mf.update(M, cov)
            last = F
            truth.append(T), meas.append(M), fused.append(F)
        return truth, meas, fused, mf

    def test_shapes_and_a_valid_pose(self):
        _, _, fused, mf = self._run(10)
        assert fused[-1].shape == (4, 4) and np.allclose(fused[-1][:3, :3] @ fused[-1][:3, :3].T, np.eye(3))
        assert mf.P.shape == (12, 12) and np.allclose(mf.P, mf.P.T)

    def test_smooths_white_noise(self):
        truth, meas, fused, mf = self._run()
        raw = np.mean([np.linalg.norm(m[:3, 3] - t[:3, 3]) for m, t in zip(meas[20:], truth[20:], strict=True)])
        out = np.mean([np.linalg.norm(f[:3, 3] - t[:3, 3]) for f, t in zip(fused[20:], truth[20:], strict=True)])
        assert out < 0.7 * raw, (out, raw)
        assert np.allclose(mf.v, [0.3, 0, 0], atol=0.1) and np.allclose(mf.w, [0, 0.2, 0], atol=0.1)

    def test_exact_measurements_pass_through(self):
        truth, _, fused, _ = self._run(noise=0.0, cov=np.eye(6) * 1e-12)
        assert max(np.linalg.norm(f[:3, 3] - t[:3, 3]) for f, t in zip(fused, truth, strict=True)) < 1e-5

    def test_weak_direction_leans_on_the_motion(self):
        """A measurement known only loosely along x moves the pose less along x than along y."""
        _, _, fused, mf = self._run(30)
        guess = mf.predict(fused[-1], 30 * DT_DEFAULT)
        M = _pose(guess[:3, 3] + [0.03, 0.003, 0.0], so3_log(guess[:3, :3]))
        F = mf.update(M, np.diag([0.05 ** 2, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6]))
        d = F[:3, 3] - guess[:3, 3]
        assert d[0] < 0.2 * 0.03 and d[1] > 0.5 * 0.003, d

    def test_gate_takes_the_measurement_and_restarts_the_velocity(self):
        _, _, fused, mf = self._run(30)
        guess = mf.predict(fused[-1], 30 * DT_DEFAULT)
        M = _pose(guess[:3, 3] + [0.5, 0, 0], so3_log(guess[:3, :3]))  # 50 cm off at 1 cm noise
        cov = np.eye(6) * 1e-4
        y = M[:3, 3] - guess[:3, 3]
        assert y @ y / (1e-4 + mf.P[0, 0]) > GATE
        assert np.array_equal(mf.update(M, cov), M) and not mf.v.any() and not mf.w.any()

    def _twins(self, n):
        """A filter after ``n`` frames and its copy through state_dict, both predicting the next."""
        _, _, fused, mf = self._run(n)
        mf2 = MotionFilter()
        mf2.load_state_dict(mf.state_dict())
        for m in (mf, mf2):
            m.predict(fused[-1], n * DT_DEFAULT)
        return fused, mf, mf2

    def test_redo_replaces_the_update(self):
        _, mf, mf2 = self._twins(30)
        cov = np.eye(6) * 1e-5
        a = mf.update(_pose([9.0 * DT_DEFAULT + 0.01, 0, 0]), cov)
        b = mf.update(_pose([9.0 * DT_DEFAULT, 0, 0]), cov, redo=True)
        c = mf2.update(_pose([9.0 * DT_DEFAULT, 0, 0]), cov)
        assert not np.allclose(a, b) and np.allclose(b, c) and len(mf.raw) == len(mf2.raw)

    def test_state_dict_round_trip(self):
        fused, mf, mf2 = self._twins(20)
        cov = np.eye(6) * 1e-5
        assert np.array_equal(mf.update(fused[-1], cov), mf2.update(fused[-1], cov))

    def test_timestamps_set_the_step(self):
        mf = MotionFilter()
        mf.restart(10.0)
        mf.v = np.array([1.0, 0, 0])
        assert np.isclose(mf.predict(np.eye(4), 10.5)[0, 3], 0.5)
        assert np.isclose(mf.predict(np.eye(4), None)[0, 3], DT_DEFAULT)  # no timestamp: the default step

    @pytest.mark.parametrize("bad", [np.full((6, 6), np.inf)])
    def test_unknown_covariance_takes_the_measurement(self, bad):
        _, _, fused, mf = self._run(10)
        mf.predict(fused[-1], 10 * DT_DEFAULT)
        M = _pose([0.1, 0, 0])
        assert np.array_equal(mf.update(M, bad), M)
