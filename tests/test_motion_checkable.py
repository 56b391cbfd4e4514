"""motion/checkable.py: what of the observation the map can judge, and the blur-forgiving render."""

from types import SimpleNamespace

import numpy as np

from dynslam_cli.motion.checkable import (bounded_extent, checkable_depth, closest_rendered, depth_cell, keyframe_visibility,
                                          seen_through)
from dynslam_cli.slam.keyframes import DEPTH_STRIDE, subsample_depth

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


INTR_WH = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=64, height=48)


def _kf(depth, pose=None):
    return SimpleNamespace(pose_c2w=np.eye(4) if pose is None else pose, depth_raw_small=subsample_depth(depth))


class TestSeenThrough:
    def test_new_in_front_of_what_the_newest_keyframe_saw(self):
        wall = np.full((48, 64), 2.0, np.float32)
        now = wall.copy()
        now[10:30, 10:30] = 1.0  # something stands 1 m in front of the wall the keyframe saw
        out = seen_through(now, np.ones((48, 64), bool), np.eye(4), INTR_WH, [_kf(wall)], 0.3)
        assert out.shape == (48, 64) and out[20, 20] and not out[40, 50]
        assert not seen_through(now, np.ones((48, 64), bool), np.eye(4), INTR_WH, [_kf(wall)], 1.5)[20, 20]

    def test_only_where_asked_and_with_depth(self):
        wall = np.full((48, 64), 2.0, np.float32)
        now = wall.copy()
        now[10:30, 10:30] = 1.0
        now[15, 15] = 0.0  # a sensor hole
        where = np.zeros((48, 64), bool)
        where[10:20] = True
        out = seen_through(now, where, np.eye(4), INTR_WH, [_kf(wall)], 0.3)
        assert out[12, 12] and not out[25, 25] and not out[15, 15]

    def test_any_of_the_last_keyframes(self):
        wall = np.full((48, 64), 2.0, np.float32)
        now = wall.copy()
        now[10:30, 10:30] = 1.0
        every = np.ones((48, 64), bool)
        # a keyframe before saw the wall there, the newest the thing already standing: one of them saw through
        assert seen_through(now, every, np.eye(4), INTR_WH, [_kf(wall), _kf(now)], 0.3)[20, 20]
        # only the last `newest` keyframes count (the keyframes keep every 4th pixel: the thing's outermost
        # pixels may land on the wall beside it)
        assert not seen_through(now, every, np.eye(4), INTR_WH, [_kf(wall), _kf(now)], 0.3, newest=1)[12:28, 12:28].any()
        assert not seen_through(now, every, np.eye(4), INTR_WH, [_kf(wall)] + [_kf(now)] * 3, 0.3)[12:28, 12:28].any()
        # a keyframe without depth there (a hole) saw nothing
        holed = wall.copy()
        holed[8:32, 8:32] = 0.0
        assert not seen_through(now, every, np.eye(4), INTR_WH, [_kf(holed)], 0.3).any()

    def test_posed_keyframes(self):
        wall = np.full((48, 64), 2.0, np.float32)
        now = wall.copy()
        now[10:30, 20:40] = 1.0
        left = np.eye(4)
        left[0, 3] = -0.4  # the keyframe stood 0.4 m to the left (10 px at 2 m): the wall is the same plane
        out = seen_through(now, np.ones((48, 64), bool), np.eye(4), INTR_WH, [_kf(wall, left)], 0.3)
        assert out[20, 30] and not out[40, 30]

    def test_without_keyframes_nothing(self):
        d = np.ones((48, 64), np.float32)
        assert not seen_through(d, np.ones((48, 64), bool), np.eye(4), INTR_WH, [], 0.3).any()
        kf = SimpleNamespace(pose_c2w=np.eye(4), depth_raw_small=None)
        assert not seen_through(d, np.ones((48, 64), bool), np.eye(4), INTR_WH, [kf], 0.3).any()

    def test_same_as_the_numpy_expression(self):
        """The kernel against the whole-array numpy expression it replaces, on random posed keyframes."""
        from dynslam_cli.geometry.camera import pixel_dirs, transform
        from dynslam_cli.geometry.lie import se3_exp_np
        from dynslam_cli.motion.checkable import project_into

        rng = np.random.default_rng(0)
        H, W = 48, 64
        for _ in range(5):
            now = rng.uniform(0.5, 3.0, (H, W)).astype(np.float32)
            now[rng.random((H, W)) < 0.1] = 0.0
            where = rng.random((H, W)) < 0.7
            pose = se3_exp_np(rng.normal(0, 0.05, 6))
            kfs = [_kf(rng.uniform(0.0, 4.0, (H, W)).astype(np.float32), se3_exp_np(rng.normal(0, 0.05, 6)))
                   for _ in range(4)]
            ref = np.zeros((H, W), bool)
            v, u = np.nonzero(where & (now > 0))
            world = transform(pose, pixel_dirs(u, v, 50.0, 50.0, 31.5, 23.5) * now[v, u][:, None])
            for kf in kfs[-3:]:
                pc, pu, pv, inside = project_into(world, kf.pose_c2w, INTR_WH, W, H)
                small = kf.depth_raw_small.astype(np.float32)
                iu = np.clip(np.round(np.where(inside, pu, 0) / 4).astype(np.int64), 0, small.shape[1] - 1)
                iv = np.clip(np.round(np.where(inside, pv, 0) / 4).astype(np.int64), 0, small.shape[0] - 1)
                d_kf = small[iv, iu]
                hit = inside & (d_kf > 0) & (d_kf > pc[:, 2] + 0.3)
                ref[v[hit], u[hit]] = True
            out = seen_through(now, where, pose, INTR_WH, kfs, 0.3)
            assert ref.any() and not ref.all()
            np.testing.assert_array_equal(out, ref)


class TestBoundedExtent:
    def test_extent_taken_only_where_something_new_stands(self):
        wall = np.full((48, 64), 2.0, np.float32)
        now = wall.copy()
        now[10:30, 10:30] = 1.0  # a mover in front of the wall
        ids = np.ones((48, 64), np.int32)  # the wall is segment 1
        ids[12:28, 12:28] = 2  # the mover's segment misses its 2-px outline band ...
        extent = ids.copy()
        extent[10:30, 10:30] = 2  # ... which its extent takes back
        extent[40:44, 40:44] = 2  # and a patch of the wall its depth would not continue into
        out = bounded_extent(ids, extent, now, np.eye(4), INTR_WH, [_kf(wall)], 0.3)
        assert (out[10:30, 10:30] == 2).all()  # the outline is in front of the wall the keyframe saw
        assert (out[40:44, 40:44] == 1).all()  # the wall patch keeps its own segment
        assert out.dtype == ids.dtype and ids[10, 10] == 1  # ids untouched

    def test_same_ids_when_nothing_differs_or_nothing_is_new(self):
        d = np.full((48, 64), 2.0, np.float32)
        ids = np.ones((48, 64), np.int32)
        assert bounded_extent(ids, ids.copy(), d, np.eye(4), INTR_WH, [_kf(d)], 0.3) is ids
        ext = ids.copy()
        ext[:5] = 2
        assert bounded_extent(ids, ext, d, np.eye(4), INTR_WH, [_kf(d)], 0.3) is ids


def test_depth_cell_is_the_nearest_subsampled_pixel_clipped_to_the_map():
    u = np.array([0.0, 1.9, 2.1, 7.0, 1000.0, -5.0])
    v = np.array([0.0, 0.0, 6.0, 9.9, 1000.0, -5.0])
    iv, iu = depth_cell(u, v, (3, 4))
    assert DEPTH_STRIDE == 4 and iv.dtype == np.int64 and iu.dtype == np.int64
    assert iu.tolist() == [0, 0, 1, 2, 3, 0] and iv.tolist() == [0, 0, 2, 2, 2, 0]
    small = subsample_depth(np.arange(12 * 16, dtype=np.float32).reshape(12, 16))
    iv, iu = depth_cell(np.array([8.0]), np.array([4.0]), small.shape)  # a kept pixel finds itself
    assert float(small[iv[0], iu[0]]) == 4 * 16 + 8
