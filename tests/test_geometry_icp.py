import numpy as np

from dynslam_cli.geometry.icp import downsample_depth, icp_depth, level_intrinsics
from dynslam_cli.geometry.lie import inv_np, se3_exp_np
from dynslam_cli.slam.toyscene import TinyIntrinsics, render

INTR = TinyIntrinsics(160, 120, f=130.0)
K = (INTR.fx, INTR.fy, INTR.cx, INTR.cy)


def _angle(T):
    return np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))


def test_icp_recovers_a_known_small_motion():
    p0 = se3_exp_np([0.1, 0.05, 0.2, 0.02, 0.1, 0.0])
    motion = se3_exp_np([0.02, -0.015, 0.01, 0.02, -0.03, 0.01])  # ~2.7 cm, ~2.1 deg, in the camera frame
    p1 = p0 @ motion
    _, d0 = render(p0, INTR)
    _, d1 = render(p1, INTR)
    res = icp_depth(d0, d1, K, factors=(2, 1), iters=(10, 6))
    assert res.ok and res.fraction > 0.5
    err = inv_np(motion) @ res.T
    assert np.linalg.norm(err[:3, 3]) < 1e-3 and _angle(err) < 0.05
    # the motion was really recovered, not just the identity
    assert np.linalg.norm(res.T[:3, 3]) > 0.02


def test_icp_with_a_point_budget_still_recovers_the_motion():
    p0 = se3_exp_np([0.1, 0.05, 0.2, 0.02, 0.1, 0.0])
    motion = se3_exp_np([0.02, -0.015, 0.01, 0.02, -0.03, 0.01])
    _, d0 = render(p0, INTR)
    _, d1 = render(p0 @ motion, INTR)
    res = icp_depth(d0, d1, K, factors=(2, 1), iters=(10, 6), max_points=2000)  # of ~19 000
    err = inv_np(motion) @ res.T
    assert res.ok and res.inliers <= 2000 and np.linalg.norm(err[:3, 3]) < 2e-3 and _angle(err) < 0.1


def test_icp_from_a_good_init_stays_and_fails_cleanly_without_depth():
    p0 = np.eye(4)
    motion = se3_exp_np([0.01, 0.0, 0.0, 0.0, 0.01, 0.0])
    _, d0 = render(p0, INTR)
    _, d1 = render(p0 @ motion, INTR)
    res = icp_depth(d0, d1, K, init=motion, factors=(4, 2), iters=(4, 3))
    assert res.ok and np.linalg.norm((inv_np(motion) @ res.T)[:3, 3]) < 2e-3
    bad = icp_depth(d0, np.zeros_like(d1), K, factors=(4, 2), iters=(4, 3))
    assert not bad.ok and np.allclose(bad.T, np.eye(4))


def test_downsample_depth_drops_edges_and_holes():
    d = np.ones((8, 8), np.float32)
    d[:4, :4] = 0          # a hole block
    d[4:, 4:6] = 3.0       # an edge inside the bottom-right block
    out = downsample_depth(d, 4)
    assert out.shape == (2, 2)
    assert out[0, 0] == 0 and out[1, 1] == 0 and out[0, 1] == 1 and out[1, 0] == 1
    fx, fy, cx, cy = level_intrinsics(100.0, 100.0, 7.5, 3.5, 4)
    assert (fx, cx, cy) == (25.0, 1.5, 0.5)
