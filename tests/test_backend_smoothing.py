import numpy as np
import pytest

from dynslam_cli.backend import smoothing
from dynslam_cli.backend.smoothing import smooth_centres, smooth_poses
from dynslam_cli.geometry.lie import so3_exp_np


def _track(n=200, fps=30.0, seed=0, jerk=False):
    """A smooth camera path (m) at ``fps``: a slow curve, or with ``jerk`` a fast shaking one."""
    t = np.arange(n) / fps
    if jerk:
        x = np.stack([0.05 * np.sin(2 * np.pi * 3.0 * t), 0.05 * np.cos(2 * np.pi * 2.5 * t), 0.3 * t], 1)
    else:
        x = np.stack([0.2 * np.sin(0.5 * t), 0.1 * t, 0.05 * np.cos(0.3 * t)], 1)
    return t, x


def _rms(a, b):
    return float(np.sqrt(((a - b) ** 2).sum(1).mean()))


class TestSmoothCentres:
    def test_shapes_and_report(self):
        t, x = _track()
        z = x + np.random.default_rng(0).normal(0, 0.005, x.shape)
        sm = smooth_centres(t, z)
        assert sm.centres.shape == z.shape and np.isfinite(sm.centres).all()
        assert sm.q in smoothing.Q_GRID
        assert 0.003 < sm.noise_sd < 0.008  # the white noise it measured (0.5 cm per axis)

    def test_white_noise_is_taken_off(self):
        t, x = _track()
        z = x + np.random.default_rng(1).normal(0, 0.005, x.shape)
        sm = smooth_centres(t, z)
        assert _rms(sm.centres, x) < 0.5 * _rms(z, x)

    def test_the_first_frame_is_held(self):
        t, x = _track()
        z = x + np.random.default_rng(2).normal(0, 0.005, x.shape)
        assert np.allclose(smooth_centres(t, z).centres[0], z[0], atol=1e-6)

    def test_a_jerky_camera_is_not_smoothed_away(self):
        rng = np.random.default_rng(3)
        t, smooth = _track()
        _, jerky = _track(jerk=True)
        q_smooth = smooth_centres(t, smooth + rng.normal(0, 0.003, smooth.shape)).q
        z = jerky + rng.normal(0, 0.003, jerky.shape)
        sm = smooth_centres(t, z)
        # a larger spectral density, or (where the shaking hides the noise) no smoothing at all
        assert np.isnan(sm.q) or sm.q > 10 * q_smooth
        assert _rms(sm.centres, jerky) <= _rms(z, jerky)
        # shaking the noise is still measurable under: a larger spectral density, the noise still taken off
        _, mild = _track()
        mild = mild + np.stack([0.01 * np.sin(2 * np.pi * 2.0 * t), np.zeros_like(t), np.zeros_like(t)], 1)
        zm = mild + rng.normal(0, 0.003, mild.shape)
        sm = smooth_centres(t, zm)
        assert sm.q > 10 * q_smooth and _rms(sm.centres, mild) < _rms(zm, mild)

    def test_one_wrong_frame_does_not_drag_its_neighbours(self, monkeypatch):
        t, x = _track()
        z = x + np.random.default_rng(4).normal(0, 0.003, x.shape)
        z[100] += [0.07, 0.0, 0.0]  # a 7 cm wrong pose
        robust = smooth_centres(t, z)
        assert robust.downweighted >= 1
        monkeypatch.setattr(smoothing, "ROUNDS", 1)  # one fit, every frame weighted alike
        plain = smooth_centres(t, z)
        near = slice(95, 106)
        assert _rms(robust.centres[near], x[near]) < 0.7 * _rms(plain.centres[near], x[near])

    def test_a_short_excursion_at_the_end_is_left_out(self):
        # two frames 15 cm off that come back for the last frame (a pose tracked on movers the masks
        # missed): the fit rejects them; a Huber weight, whose pull stays bounded but never goes,
        # left them 3-4 cm off and dragged the frames before them
        t, x = _track()
        z = x + np.random.default_rng(8).normal(0, 0.003, x.shape)
        z[-3:-1] += [0.15, 0.0, 0.0]
        sm = smooth_centres(t, z)
        err = np.linalg.norm(sm.centres - x, axis=1)
        assert err[-3:-1].max() < 0.01 and err[-20:].max() < 0.01
        assert sm.downweighted >= 2

    def test_the_fits_stop_once_the_weights_settle(self, monkeypatch):
        t, x = _track()
        z = x + np.random.default_rng(9).normal(0, 0.003, x.shape)
        fits = []
        real = smoothing._rts
        monkeypatch.setattr(smoothing, "_rts", lambda *a: fits.append(1) or real(*a))
        smooth_centres(t, z)
        assert 2 <= len(fits) < smoothing.ROUNDS

    def test_uneven_timestamps(self):
        t, x = _track()
        keep = np.sort(np.random.default_rng(5).choice(len(t), 120, replace=False))
        z = x[keep] + np.random.default_rng(6).normal(0, 0.005, (len(keep), 3))
        sm = smooth_centres(t[keep], z)
        assert _rms(sm.centres, x[keep]) < 0.6 * _rms(z, x[keep])

    @pytest.mark.parametrize("n", [1, 5, 7])
    def test_too_short_is_returned_as_it_is(self, n):
        t, x = _track(n)
        sm = smooth_centres(t, x + 0.01)
        assert np.array_equal(sm.centres, x + 0.01) and np.isnan(sm.q)

    def test_a_noise_free_track_is_returned_as_it_is(self):
        t = np.arange(50) / 30.0
        x = np.stack([0.1 * t, 0.2 * t, np.zeros_like(t)], 1)  # constant velocity: no second differences
        sm = smooth_centres(t, x)
        assert np.array_equal(sm.centres, x) and sm.noise_sd < smoothing.NOISE_FLOOR and np.isnan(sm.q)


class TestSmoothPoses:
    def test_orientations_kept_centres_smoothed(self):
        t, x = _track(60)
        rng = np.random.default_rng(7)
        poses = np.tile(np.eye(4), (len(t), 1, 1))
        for i in range(len(t)):
            poses[i, :3, :3] = so3_exp_np(rng.normal(0, 0.3, 3))
        poses[:, :3, 3] = x + rng.normal(0, 0.005, x.shape)
        out, sm = smooth_poses(t, poses)
        assert out.shape == poses.shape and np.array_equal(out[:, :3, :3], poses[:, :3, :3])
        assert np.array_equal(out[:, :3, 3], sm.centres) and np.array_equal(out[:, 3], poses[:, 3])
        assert _rms(out[:, :3, 3], x) < _rms(poses[:, :3, 3], x)
