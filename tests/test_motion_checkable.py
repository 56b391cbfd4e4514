"""motion/checkable.py: what of the observation the map can judge, and the blur-forgiving render."""

from types import SimpleNamespace

import numpy as np

from dynslam_cli.motion.checkable import checkable_depth, closest_rendered, keyframe_visibility
from dynslam_cli.slam.keyframes import subsample_depth

INTR = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)


def test_checkable_depth_drops_edges_and_unseen_space():
    depth = np.full((48, 64), 2.0, np.float32)
    depth[20:30, 20:30] = 1.0  # a box in front of a wall
    kf = SimpleNamespace(pose_c2w=np.eye(4), depth_small=None)
    out, fwd = checkable_depth(depth, np.eye(4), INTR, [kf], 0.3, step=1)
    assert out[25, 25] == 1.0 and out[5, 5] == 2.0  # interiors kept
    assert out[20, 25] == 0 and out[19, 25] == 0 and out[25, 30] == 0  # both sides of the step dropped
    assert fwd.all()  # without a stored depth map the whole frustum counts as observed
    # the camera moved 1 m to the right: what it sees on its right was never in a keyframe's view
    moved = np.eye(4)
    moved[0, 3] = 1.0
    out2, _ = checkable_depth(depth, moved, INTR, [kf], 0.3, step=1)
    assert out2[5, 5] > 0 and np.all(out2[:, -5:] == 0)
    # only the last frustum_keyframes keyframes count: an older one that saw the right side does not
    right = np.eye(4)
    right[0, 3] = 1.0
    old = SimpleNamespace(pose_c2w=right, depth_small=None)
    assert np.all(checkable_depth(depth, moved, INTR, [old, kf], 0.3, step=1)[0][:, -5:] > 0)
    assert np.all(checkable_depth(depth, moved, INTR, [old, kf], 0.3, step=1, frustum_keyframes=1)[0][:, -5:] == 0)
    # no keyframes: every valid pixel off the edges is judged, forward included
    out3, fwd3 = checkable_depth(depth, moved, INTR, [], 0.3, step=1)
    np.testing.assert_array_equal(fwd3, out3 > 0)
    assert out3[:, -5:].all()


def test_checkable_depth_leaves_out_the_border_the_map_was_never_taught():
    depth = np.full((48, 64), 2.0, np.float32)
    kf = SimpleNamespace(pose_c2w=np.eye(4), depth_small=subsample_depth(depth))
    out, fwd = checkable_depth(depth, np.eye(4), INTR, [kf], 0.3, step=1, border=4)
    assert out[24, 32] == 2.0 and fwd[24, 32]
    assert not out[:, :4].any() and not out[:, -4:].any() and not out[:4].any() and not out[-4:].any()
    assert not fwd[:, :4].any() and not fwd[:4].any()
    # the camera moved right: what was at the keyframe's right edge is now inside the view, still untaught
    moved = np.eye(4)
    moved[0, 3] = 0.2  # 5 px at 2 m and fx 50
    out2, _ = checkable_depth(depth, moved, INTR, [kf], 0.3, step=1, border=4)
    assert out2[24, 30].all() and not out2[24, 55:].any()
    # no border: the whole view as before
    assert checkable_depth(depth, np.eye(4), INTR, [kf], 0.3, step=1)[0][:, 3].all()


def test_checkable_depth_knows_what_keyframes_saw_behind_occluders():
    seen = np.full((48, 64), 2.0, np.float32)
    seen[20:32, 20:32] = 1.0  # the keyframe saw a box in front of the wall
    kf = SimpleNamespace(pose_c2w=np.eye(4), depth_small=subsample_depth(seen))
    now = np.full((48, 64), 2.0, np.float32)  # the box has gone ...
    now[4:12, 40:52] = 1.5  # ... and something new stands in front of the wall
    out, fwd = checkable_depth(now, np.eye(4), INTR, [kf], 0.3, step=1)
    assert not fwd[26, 26] and out[26, 26] == 2.0  # the wall behind the old box: never observed
    assert fwd[8, 46] and fwd[40, 5]  # free space / the wall the keyframe saw
    # a wider occlusion margin: 1 m behind the box counts as observed
    _, fwd_wide = checkable_depth(now, np.eye(4), INTR, [kf], 1.5, step=1)
    assert fwd_wide[26, 26]


def test_keyframe_visibility_without_keyframes_sees_nothing():
    frustum, observed = keyframe_visibility(np.ones((8, 10), np.float32), np.eye(4), INTR, [])
    assert frustum.shape == observed.shape == (8, 10) and not frustum.any() and not observed.any()


def test_closest_rendered_forgives_blurred_edges_not_movers():
    ren = np.full((20, 20), 3.0, np.float32)
    ren[5:15, 5:10] = 1.0  # the map's object, one pixel narrower than the observation
    obs = np.full((20, 20), 3.0, np.float32)
    obs[5:15, 5:11] = 1.0
    obs[2:6, 14:18] = 0.8  # a mover in front of the wall
    out = closest_rendered(ren, obs, radius=1)
    assert out[8, 10] == 1.0  # edge pixel: a neighbour agrees
    assert out[3, 16] == 3.0  # mover interior: nothing near agrees, still 2.2 m inconsistent
    np.testing.assert_array_equal(closest_rendered(ren, obs, radius=0), ren)


def _visibility_every_keyframe(depth, pose_c2w, intr, keyframes, step, margin, border):
    """keyframe_visibility as its definition reads: every point projected into every keyframe."""
    from dynslam_cli.geometry.camera import pixel_dirs, transform
    from dynslam_cli.motion.checkable import project_into
    from dynslam_cli.slam.keyframes import DEPTH_STRIDE

    H, W = depth.shape
    vs, us = np.mgrid[0:H:step, 0:W:step]
    z = depth[::step, ::step]
    world = transform(pose_c2w, pixel_dirs(us.ravel(), vs.ravel(), intr.fx, intr.fy, intr.cx, intr.cy) * z.reshape(-1, 1))
    frustum, observed = np.zeros(len(world), bool), np.zeros(len(world), bool)
    for kf in keyframes:
        pc, u, v, inside = project_into(world, kf.pose_c2w, intr, W, H, border)
        frustum |= inside
        if kf.depth_small is not None:
            hs, ws = kf.depth_small.shape
            iu = np.clip(np.round(u / DEPTH_STRIDE).astype(np.int64), 0, ws - 1)
            iv = np.clip(np.round(v / DEPTH_STRIDE).astype(np.int64), 0, hs - 1)
            d_kf = kf.depth_small[iv, iu].astype(np.float32)
            inside &= ~((d_kf <= 0) | (d_kf < pc[:, 2] - margin))
        observed |= inside
    return frustum.reshape(z.shape), observed.reshape(z.shape)


def test_keyframe_visibility_equals_projecting_every_point_into_every_keyframe():
    from dynslam_cli.geometry.lie import se3_exp_np

    rng = np.random.default_rng(3)
    H, W = 48, 64
    depth = (2.0 + rng.uniform(-0.3, 0.3, (H, W))).astype(np.float32)
    depth[rng.random((H, W)) < 0.05] = 0
    kfs = []
    for i in range(7):
        pose = se3_exp_np(np.concatenate([rng.normal(0, 0.25, 3), rng.normal(0, 0.15, 3)]))
        small = subsample_depth((1.5 + rng.uniform(0, 1.2, (H, W))).astype(np.float32)) if i % 3 else None
        kfs.append(SimpleNamespace(pose_c2w=pose, depth_small=small))
    for step, border in ((1, 0), (4, 3)):
        frustum, observed = keyframe_visibility(depth, np.eye(4), INTR, kfs, step, 0.3, border)
        ref_f, ref_o = _visibility_every_keyframe(depth, np.eye(4), INTR, kfs, step, 0.3, border)
        assert 0 < ref_o.sum() < ref_f.sum() < ref_f.size  # every case occurs
        assert np.array_equal(frustum[::step, ::step], ref_f) and np.array_equal(observed[::step, ::step], ref_o)


def test_samples_without_depth_are_the_camera_centre_seen_or_not():
    # every sample without depth back-projects to the frame's camera centre: a keyframe 1 m behind the frame,
    # looking the same way, sees that point; one 1 m in front of it does not
    rng = np.random.default_rng(4)
    H, W = 48, 64
    depth = (2.0 + rng.uniform(-0.3, 0.3, (H, W))).astype(np.float32)
    depth[rng.random((H, W)) < 0.3] = 0
    wall = subsample_depth(np.full((H, W), 2.5, np.float32))
    for dz, seen in ((-1.0, True), (1.0, False)):
        pose = np.eye(4)
        pose[2, 3] = dz
        kfs = [SimpleNamespace(pose_c2w=pose, depth_small=wall)]
        frustum, observed = keyframe_visibility(depth, np.eye(4), INTR, kfs, 2, 0.3, 0)
        ref_f, ref_o = _visibility_every_keyframe(depth, np.eye(4), INTR, kfs, 2, 0.3, 0)
        assert np.array_equal(frustum[::2, ::2], ref_f) and np.array_equal(observed[::2, ::2], ref_o)
        none = depth[::2, ::2] == 0
        assert ref_o[none].all() == seen and ref_f[none].all() == seen and ref_f[none].any() == seen
