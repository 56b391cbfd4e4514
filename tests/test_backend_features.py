"""Keypoint depth and its uncertainty (dynslam_cli.backend.features.depth_sigma)."""

import numpy as np

from dynslam_cli.backend.features import SCALE, depth_sigma


class TestDepthSigma:
    def test_flat_depth_is_the_sensor_noise(self):
        depth = np.full((5, 5), 2.0)
        s = depth_sigma(depth, np.array([2]), np.array([2]), np.array([2.0]), np.array([0]), 0.01)
        assert np.allclose(s, 0.01 * 2.0 ** 2)

    def test_a_depth_step_adds_its_size_times_the_position_uncertainty(self):
        depth = np.full((5, 5), 2.0)
        depth[2, 3] = 2.5  # one 4-neighbour 0.5 m behind
        depth[0, 0] = 9.0  # not a 4-neighbour of (2, 2): ignored
        for octave in (0, 3):
            s = depth_sigma(depth, np.array([2]), np.array([2]), np.array([2.0]), np.array([octave]), 0.01)
            assert np.allclose(s, np.hypot(0.04, 0.5 * SCALE ** octave))

    def test_holes_give_no_sigma_and_judge_nothing(self):
        depth = np.full((5, 5), 2.0)
        depth[2, 1] = 0.0  # an invalid neighbour is not a step
        s = depth_sigma(depth, np.array([2, 0]), np.array([2, 0]), np.array([2.0, 0.0]), np.array([0, 0]), 0.01)
        assert np.allclose(s, [0.04, 0.0])

    def test_image_border_is_safe(self):
        depth = np.full((4, 4), 1.0)
        s = depth_sigma(depth, np.array([0, 3]), np.array([0, 3]), np.array([1.0, 1.0]), np.array([0, 0]), 0.02)
        assert np.allclose(s, 0.02)


class TestOnDepthDiscontinuity:
    def _step(self):
        d = np.full((60, 80), 2.0, np.float32)
        d[:, :40] = 1.0  # a near surface on the left, the edge between columns 39 and 40
        return d

    def test_known_values_by_octave(self):
        from dynslam_cli.backend.features import on_depth_discontinuity

        d = self._step()
        v = np.array([30, 30, 30, 30])
        u = np.array([38, 30, 35, 47])  # at 35 two of the 13 window columns lie beyond the edge (15 %)
        octave = np.array([0, 0, 4, 4])  # FAST radius 3 px at octave 0, round(3 * 1.2^4) = 6 px at 4
        assert on_depth_discontinuity(d, v, u, octave).tolist() == [True, False, True, False]

    def test_noise_and_missing_depth_are_not_a_contour(self):
        from dynslam_cli.backend.features import on_depth_discontinuity

        rng = np.random.default_rng(0)
        d = (2.0 * (1 + 0.01 * rng.standard_normal((60, 80)))).astype(np.float32)  # 1 % noise
        d[::5, ::5] = 0  # holes
        v, u = np.array([30, 10]), np.array([30, 10])
        assert not on_depth_discontinuity(d, v, u, np.zeros(2, np.int64)).any()  # (10, 10) is a hole itself
        assert on_depth_discontinuity(d, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)).shape == (0,)
