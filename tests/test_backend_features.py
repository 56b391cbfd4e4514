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
