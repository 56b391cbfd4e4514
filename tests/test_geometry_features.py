"""Feature-based RGB-D odometry (ORB + PnP/RANSAC) on an analytic textured plane."""

import cv2
import numpy as np
import pytest

from dynslam_cli.geometry.features import FeatureOdometry, FeatureSet
from dynslam_cli.geometry.lie import inv_np, se3_exp_np

W, H, F = 320, 240, 260.0
NEAR_Z, FAR_Z = 1.5, 2.5  # a textured step: the plane z = 1.5 m where x < 0, z = 2.5 m where x >= 0


def _texture(seed=0, n=512):
    rng = np.random.default_rng(seed)
    img = rng.random((n, n)).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min())
    return (img * 255).astype(np.uint8)


def _render(pose_c2w, tex):
    """Colour and depth of the step seen from ``pose_c2w`` (pinhole W×H, focal F; x, y in [-2, 2])."""
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    dc = np.stack([(uu - (W - 1) / 2) / F, (vv - (H - 1) / 2) / F, np.ones_like(uu)], -1)
    d = dc @ pose_c2w[:3, :3].T
    o = pose_c2w[:3, 3]
    t_near = (NEAR_Z - o[2]) / d[..., 2]  # dc has z = 1, so t is the camera-frame depth
    t_far = (FAR_Z - o[2]) / d[..., 2]
    on_near = o[0] + t_near * d[..., 0] < 0
    t = np.where(on_near, t_near, t_far)
    p = o + t[..., None] * d
    t = np.where(on_near | (p[..., 0] >= 0), t, 0.0)  # rays through the step's gap see nothing
    n = tex.shape[0]
    mx = ((p[..., 0] + 2) / 4 * (n - 1)).astype(np.float32)
    my = ((p[..., 1] + 2) / 4 * (n - 1)).astype(np.float32)
    g = cv2.remap(tex, mx, my, cv2.INTER_LINEAR)
    rgb = np.repeat(g[..., None], 3, axis=2)
    return rgb, t.astype(np.float32)


def _odometry(**kw):
    return FeatureOdometry(F, F, (W - 1) / 2, (H - 1) / 2, W, **kw)


@pytest.fixture(scope="module")
def tex():
    return _texture()


def test_estimate_recovers_the_relative_pose(tex):
    p_ref = np.eye(4)
    p_cur = se3_exp_np(np.array([0.04, -0.02, 0.05, 0.02, -0.03, 0.01]))
    odo = _odometry(n_features=1500)
    rgb0, d0 = _render(p_ref, tex)
    rgb1, d1 = _render(p_cur, tex)
    ref = odo.detect(rgb0, d0)
    cur = odo.detect(rgb1, d1)
    assert len(ref) > 300 and ref.des.shape[1] == 32 and (ref.depth > 0).all()
    res = odo.estimate(ref, cur)
    assert res.ok and res.inliers >= 100
    want = inv_np(p_ref) @ p_cur
    # keypoints are located to about a pixel (8 mm at 2 m here): a few mm of error; the inverse pose would be 13 cm off
    assert np.linalg.norm(res.T[:3, 3] - want[:3, 3]) < 0.015
    dR = res.T[:3, :3].T @ want[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.5
    np.testing.assert_allclose(res.T[3], [0, 0, 0, 1])


def test_estimate_multi_poses_the_camera_in_the_world_from_several_references(tex):
    p_a = se3_exp_np(np.array([-0.05, 0.01, 0.0, 0.0, 0.02, 0.0]))
    p_b = se3_exp_np(np.array([0.06, 0.0, 0.02, 0.01, -0.02, 0.0]))
    p_cur = se3_exp_np(np.array([0.01, -0.01, 0.03, 0.01, 0.0, 0.01]))
    odo = _odometry(n_features=1500)
    mask_left = np.zeros((H, W), bool)
    mask_left[:, : W // 2] = True
    ref_a = odo.detect(*_render(p_a, tex), mask_left)  # each reference sees one half of its image
    ref_b = odo.detect(*_render(p_b, tex), ~mask_left)
    cur = odo.detect(*_render(p_cur, tex))
    res = odo.estimate_multi([(p_a, ref_a), (p_b, ref_b)], cur)
    assert res.ok and len(res.ref_inliers) == 2 and sum(res.ref_inliers) == res.inliers
    assert min(res.ref_inliers) >= 30  # both references contribute
    assert np.linalg.norm(res.T[:3, 3] - p_cur[:3, 3]) < 0.015
    dR = res.T[:3, :3].T @ p_cur[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.5
    # lifting: a reference's keypoints land on the scene, whatever its pose
    X = odo.lift(ref_b, p_b)
    assert np.all(np.abs(X[:, 2] - np.where(X[:, 0] < 0, NEAR_Z, FAR_Z)) < 0.02)
    # no references: no pose
    assert not odo.estimate_multi([], cur).ok


def test_mask_and_missing_depth_remove_keypoints(tex):
    odo = _odometry(n_features=800)
    rgb, d = _render(np.eye(4), tex)
    mask = np.zeros((H, W), bool)
    mask[:, : W // 2] = True
    fs = odo.detect(rgb, d, mask)
    assert len(fs) > 50 and (fs.uv[:, 0] < W // 2 + 1).all()
    right = np.zeros((H, W), bool)
    right[:, W // 4:] = True
    sub = fs.masked(right)
    assert 0 < len(sub) < len(fs) and (sub.uv[:, 0] >= W // 4 - 1).all()
    d_hole = d.copy()
    d_hole[:, : W // 2] = 0
    fs2 = odo.detect(rgb, d_hole)
    left = np.round(fs2.uv[:, 0]) < W // 2
    assert (fs2.depth[left] == 0).all() and (fs2.depth[~left] > 0).all()


def test_untextured_or_unrelated_frames_are_not_ok(tex):
    odo = _odometry(n_features=500)
    flat = np.full((H, W, 3), 128, np.uint8)
    d = np.full((H, W), 2.0, np.float32)
    empty = odo.detect(flat, d)
    assert len(empty) == 0
    rgb, d0 = _render(np.eye(4), tex)
    ref = odo.detect(rgb, d0)
    assert not odo.estimate(ref, empty).ok
    assert not odo.estimate(empty, ref).ok
    other = odo.detect(*_render(np.eye(4), _texture(seed=7)))
    res = odo.estimate(ref, other)
    assert not res.ok and res.inliers < 20


def test_feature_set_round_trip(tex):
    odo = _odometry(n_features=300)
    fs = odo.detect(*_render(np.eye(4), tex))
    back = FeatureSet.from_dict(fs.to_dict())
    np.testing.assert_array_equal(back.uv, fs.uv)
    np.testing.assert_array_equal(back.des, fs.des)
    np.testing.assert_array_equal(back.depth, fs.depth)
