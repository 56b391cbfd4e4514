"""motion/forget.py: keyframe rays masked after a classifier update, or marked gone for good."""

from types import SimpleNamespace

import numpy as np

from dynslam_cli.motion.forget import (carve, forget_departed, forget_near, forget_overtaken, forget_seen_through,
                                       near_ids, refresh_keyframes)
from dynslam_cli.motion.types import CheckResult
from dynslam_cli.slam.keyframes import Keyframe, KeyframeStore, subsample_depth

INTR = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)


def _keyframe(pixels, depth, pose=None, raw=None):
    n = len(depth)
    return Keyframe(0, 0.0, np.array(pixels, np.int32), np.zeros((n, 3), np.uint8), np.array(depth, np.float32),
                    np.zeros(n, np.int32), np.ones(n, bool), np.eye(4) if pose is None else pose,
                    depth_raw_small=None if raw is None else subsample_depth(raw))


def test_refresh_keyframes_masks_rays_of_dynamic_instances():
    def kf(fid, ids, usable, near=None, gone=None):
        n = len(ids)
        return Keyframe(fid, 0.0, np.zeros((n, 2), np.int32), np.zeros((n, 3), np.uint8), np.ones(n, np.float32),
                        np.array(ids, np.int32), np.array(usable, bool), near_ids=near, gone=gone)

    store = KeyframeStore()
    store.add(kf(0, [0, 1, 2, 2, -1], [True] * 5))
    store.add(kf(5, [1, 1, 0], [False] * 3))
    # ray 0 lies within the mask dilation of instance 2, ray 1 next to instance 1 only
    store.add(kf(10, [1, 1], [True, True], near=np.array([[2, 1], [1, 0]])))
    store.add(kf(15, [1, 0], [True, True], gone=np.array([False, True])))  # no instances registered: untouched
    dropped = []
    store.landmark_keyframes = SimpleNamespace(forget=lambda fid, ids: dropped.append((fid, ids.tolist())))
    dyn = {0: [2], 5: [], 10: [2], 20: [1]}  # frame 20: a backend keyframe without neural-map rays
    for fid in dyn:
        store.register_instances(fid, np.full((3, 1), float(fid)), np.zeros(3, bool))
    motion = SimpleNamespace(dynamic_ids=lambda feats, prior: np.array(dyn[int(feats[0, 0])], np.int32))
    assert refresh_keyframes(store, motion) == 3
    # the backend keyframes leave out the landmarks on dynamic instances, in registration order
    assert dropped == [(0, [2]), (5, []), (10, [2]), (20, [1])]
    assert store[0].usable.tolist() == [True, True, False, False, True]
    assert store[1].usable.tolist() == [True, True, True]  # reclassified static: remembered again
    assert store[2].usable.tolist() == [False, True]
    assert store[3].usable.tolist() == [True, True]


def test_near_ids_and_the_dilated_static_mask():
    from dynslam_cli.motion.module import MotionModule

    ids = np.zeros((20, 40), np.int32)
    ids[5:15, 10:20] = 1
    ids[5:15, 20:30] = 2
    pixels = np.array([[8, 10], [12, 10], [18, 10], [35, 10]])
    near = near_ids(ids, pixels, 0.05)  # 2 px at width 40
    assert near.tolist() == [[1, 0], [1, 1], [2, 1], [0, 0]]  # (max, min) id within 2 px
    assert near_ids(ids, pixels, 0.0).tolist() == [[0, 0], [1, 1], [1, 1], [0, 0]]  # no dilation: own id twice
    mm = MotionModule.__new__(MotionModule)
    mm.m = SimpleNamespace(mask_dilation=0.05)
    static = mm._static_mask(ids, np.array([False, True]))
    assert not static[3:17, 18:32].any() and static[10, 17] and static[10, 32] and static[2, 25]


def test_forget_near_marks_keyframe_rays_on_a_departed_surface_for_good():
    intr = INTR
    pixels = np.array([[31, 23], [10, 10], [50, 40]], np.int32)  # (u, v): centre, top-left, bottom-right
    kf = Keyframe(0, 0.0, pixels, np.zeros((3, 3), np.uint8), np.array([1.0, 3.0, 3.0], np.float32),
                  np.zeros(3, np.int32), np.ones(3, bool), np.eye(4))
    left = np.array([[-0.01, 0.0, 1.0], [0.02, 0.01, 1.01]])  # the surface seen gone: the centre ray's point
    assert forget_near([kf], left, intr, 0.05) == 1
    assert kf.gone.tolist() == [True, False, False] and kf.usable.tolist() == [False, True, True]
    assert forget_near([kf], left, intr, 0.05) == 0  # already gone
    assert forget_near([kf], np.zeros((0, 3)), intr, 0.05) == 0


def test_forget_near_gives_what_a_distance_to_every_point_gives():
    # rays all over the view, departed points in one corner of it: the rays within the radius of some point
    rng = np.random.default_rng(0)
    kfs = []
    for k in range(3):
        pixels = np.stack([rng.integers(0, 64, 400), rng.integers(0, 48, 400)], 1).astype(np.int32)
        pose = np.eye(4)
        pose[:3, 3] = rng.normal(0, 0.2, 3)
        kfs.append(Keyframe(k, 0.0, pixels, np.zeros((400, 3), np.uint8), rng.uniform(0.5, 3, 400).astype(np.float32),
                            np.zeros(400, np.int32), np.ones(400, bool), pose))
    wp = kfs[1].world_points(INTR)
    pts = wp[wp[:, 0] < np.quantile(wp[:, 0], 0.2)] + rng.normal(0, 0.03, (1, 3))
    radius = 0.08
    want = [np.sqrt(((kf.world_points(INTR)[:, None] - pts[None]) ** 2).sum(-1)).min(1) < radius for kf in kfs]
    kfs[0].gone = want[0] & (rng.random(400) < 0.5)  # some already gone: not counted again
    before = int(kfs[0].gone.sum())
    assert forget_near(kfs, pts, INTR, radius) == sum(int(w.sum()) for w in want) - before
    for kf, w in zip(kfs, want, strict=True):
        assert kf.gone.tolist() == w.tolist() and not kf.usable[w].any() and kf.usable[~w].all()
    assert 0 < sum(int(w.sum()) for w in want) < 1200  # the test holds near and far rays


def test_forget_seen_through_marks_rays_a_later_view_sees_past():
    intr = INTR
    # rays on a box at 1 m (centre), on the wall at 3 m (top-left) and on the box's edge pixel
    pixels = np.array([[31, 23], [10, 10], [40, 23]], np.int32)
    kf = Keyframe(0, 0.0, pixels, np.zeros((3, 3), np.uint8), np.array([1.0, 3.0, 1.0], np.float32),
                  np.zeros(3, np.int32), np.ones(3, bool), np.eye(4))
    now = np.full((48, 64), 3.0, np.float32)  # the box has gone: the wall behind it everywhere ...
    now[20:27, 41:48] = 0.0  # ... but for a hole right of the edge ray (within its 3 px window)
    assert forget_seen_through([kf], now, np.eye(4), intr, margin=0.3, window=3) == 1
    assert kf.gone.tolist() == [True, False, False] and kf.usable.tolist() == [False, True, True]
    assert forget_seen_through([kf], now, np.eye(4), intr, margin=0.3, window=3) == 0  # already gone
    # the box still there (same depth), or the view stopping within the margin: nothing goes
    kf2 = Keyframe(0, 0.0, pixels, np.zeros((3, 3), np.uint8), np.array([1.0, 3.0, 1.0], np.float32),
                   np.zeros(3, np.int32), np.ones(3, bool), np.eye(4))
    still = np.full((48, 64), 3.0, np.float32)
    still[15:32, 20:45] = 1.0
    assert forget_seen_through([kf2], still, np.eye(4), intr, margin=0.3) == 0
    assert forget_seen_through([kf2], np.full((48, 64), 1.2, np.float32), np.eye(4), intr, margin=0.3) == 0
    # a camera moved 0.5 m to the right sees the box's point at another pixel, through to the wall
    moved = np.eye(4)
    moved[0, 3] = 0.5
    assert forget_seen_through([kf2], np.full((48, 64), 3.0, np.float32), moved, intr, margin=0.3) == 2
    assert kf2.gone.tolist() == [True, False, True]


def test_forget_overtaken_marks_rays_whose_free_space_a_newcomer_fills():
    intr = INTR
    wall = np.full((48, 64), 3.0, np.float32)
    boxed = wall.copy()
    boxed[15:32, 20:45] = 1.5  # a box set down in front of the wall

    def keyframe(saw):
        # rays at the centre (behind where the box now stands) and at a corner, both on the wall
        return Keyframe(0, 0.0, np.array([[31, 23], [5, 5]], np.int32), np.zeros((2, 3), np.uint8),
                        np.array([3.0, 3.0], np.float32), np.zeros(2, np.int32), np.ones(2, bool), np.eye(4),
                        depth_raw_small=subsample_depth(saw))

    before = keyframe(wall)  # saw the wall through where the box now is: its centre ray is stale
    assert forget_overtaken([before], boxed, np.eye(4), intr, margin=0.3, step=2) == 1
    assert before.gone.tolist() == [True, False] and before.usable.tolist() == [False, True]
    assert forget_overtaken([before], boxed, np.eye(4), intr, margin=0.3, step=2) == 0  # already gone
    # a keyframe that saw the box there already (it did not arrive), or a wall that did not change
    assert forget_overtaken([keyframe(boxed)], boxed, np.eye(4), intr, margin=0.3, step=2) == 0
    assert forget_overtaken([keyframe(wall)], wall, np.eye(4), intr, margin=0.3, step=2) == 0
    # the box only 0.2 m in front of the wall: within the margin, nothing changes
    near = wall.copy()
    near[15:32, 20:45] = 2.8
    assert forget_overtaken([keyframe(wall)], near, np.eye(4), intr, margin=0.3, step=2) == 0
    # without the keyframe's raw depth there is nothing to judge
    bare = keyframe(wall)
    bare.depth_raw_small = None
    assert forget_overtaken([bare], boxed, np.eye(4), intr, margin=0.3, step=2) == 0


def test_forget_departed_marks_the_rays_on_a_flagged_segment_that_left():
    # the map rendered (at half resolution) a box at 1 m in segment 1; the camera now sees the wall at 3 m there
    rendered = np.full((24, 32), 3.0, np.float32)
    rendered[8:16, 12:20] = 1.0
    rids = np.zeros((24, 32), np.int32)
    rids[8:16, 12:20] = 1
    observed = np.full((48, 64), 3.0, np.float32)
    res = SimpleNamespace(rendered_ids=rids, rendered_flagged=np.array([1]))
    kf = _keyframe([[31, 23], [5, 5]], [1.0, 3.0])  # a ray on the box, one on the wall

    def departed(r=res, radius=0.05, obs=observed):
        return forget_departed(r, obs, rendered, np.eye(4), [kf], INTR, 0.3, radius)

    assert departed(radius=0.0) == 0 and kf.gone is None  # run.forget_radius 0: off
    assert departed(r=SimpleNamespace(rendered_ids=rids, rendered_flagged=np.zeros(0, np.int64))) == 0
    assert departed(r=None) == 0 and departed(obs=np.full((48, 64), 1.2, np.float32)) == 0  # within t_d
    assert departed() == 1
    assert kf.gone.tolist() == [True, False] and kf.usable.tolist() == [False, True]
    # a CheckResult without a rendered segmentation judges nothing
    empty = CheckResult(observed_moving=np.zeros(0, bool), forward=np.zeros(0, bool), backward=np.zeros(0, bool),
                        fractions=np.zeros(0, np.float32), background_forward=0.0, background_moving=False)
    assert departed(r=empty) == 0


def test_carve_judges_the_earlier_keyframes_from_the_newest_on_its_static_pixels():
    wall = np.full((48, 64), 3.0, np.float32)
    boxed = wall.copy()
    boxed[15:32, 20:45] = 1.5
    newest = _keyframe([[5, 5]], [3.0])

    def scene():  # one keyframe saw the box (now gone), one the wall where a box now stands
        return [_keyframe([[31, 23], [5, 5]], [1.5, 3.0]), _keyframe([[31, 23]], [3.0], raw=wall)]

    kfs = scene()
    assert carve(kfs + [newest], INTR, wall, np.ones_like(wall, bool), 0.3, 64) == 1  # seen through the box
    assert kfs[0].gone.tolist() == [True, False] and newest.gone is None  # the newest keyframe is the judge
    kfs = scene()
    assert carve(kfs + [newest], INTR, boxed, np.ones_like(wall, bool), 0.3, 64) == 1  # the box arrived
    assert kfs[1].gone.tolist() == [True]
    kfs = scene()
    assert carve(kfs + [newest], INTR, wall, np.zeros_like(wall, bool), 0.3, 64) == 0  # no static pixels
    assert carve(kfs + [newest], INTR, wall, np.ones_like(wall, bool), 0.0, 64) == 0  # run.carve_margin 0: off
    assert carve([newest], INTR, wall, np.ones_like(wall, bool), 0.3, 64) == 0  # nothing earlier
