"""motion/forget.py: keyframe rays masked after a classifier update, or marked gone for good."""

from types import SimpleNamespace

import numpy as np

from dynslam_cli.motion.forget import (DepartedPlaces, departed_points, departed_surface, forget_near, near_ids,
                                      refresh_keyframes)
from dynslam_cli.motion.types import CheckResult
from dynslam_cli.slam.keyframes import DEPTH_STRIDE, Keyframe, KeyframeStore

INTR = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)


def _keyframe(pixels, depth):
    n = len(depth)
    return Keyframe(0, 0.0, np.array(pixels, np.int32), np.zeros((n, 3), np.uint8), np.array(depth, np.float32),
                    np.zeros(n, np.int32), np.ones(n, bool), np.eye(4))


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


class TestDepartedPoints:
    """departed_points: the rendered surface of a flagged segment where the observation lies behind it by t_d."""

    # the map rendered (at half resolution) a box at 1 m in segment 1; the camera now sees the wall at 3 m there
    RENDERED = np.full((24, 32), 3.0, np.float32)
    RENDERED[8:16, 12:20] = 1.0
    RIDS = np.zeros((24, 32), np.int32)
    RIDS[8:16, 12:20] = 1
    OBSERVED = np.full((48, 64), 3.0, np.float32)

    def _res(self, flagged=(1,)):
        return SimpleNamespace(rendered_ids=self.RIDS, rendered_flagged=np.array(flagged, np.int64))

    def test_points_on_the_box_at_its_rendered_depth(self):
        pts = departed_points(self._res(), self.OBSERVED, self.RENDERED, np.eye(4), INTR, 0.3)
        assert pts.shape == (64, 3) and np.allclose(pts[:, 2], 1.0)
        # the box's pixels (12..19, 8..15 at half resolution) seen from the centre of the full-resolution image
        assert np.all(np.abs(pts[:, 0]) < 0.2) and np.all(np.abs(pts[:, 1]) < 0.2)
        moved = np.eye(4)
        moved[:3, 3] = [1.0, 2.0, 3.0]  # world points follow the camera's pose
        assert np.allclose(departed_points(self._res(), self.OBSERVED, self.RENDERED, moved, INTR, 0.3), pts + [1, 2, 3])

    def test_nothing_without_a_flagged_segment_or_within_t_d(self):
        none = departed_points(self._res(()), self.OBSERVED, self.RENDERED, np.eye(4), INTR, 0.3)
        assert none.shape == (0, 3)
        assert departed_points(None, self.OBSERVED, self.RENDERED, np.eye(4), INTR, 0.3).shape == (0, 3)
        near = np.full((48, 64), 1.2, np.float32)
        assert departed_points(self._res(), near, self.RENDERED, np.eye(4), INTR, 0.3).shape == (0, 3)
        # a CheckResult without a rendered segmentation judges nothing
        empty = CheckResult(observed_moving=np.zeros(0, bool), forward=np.zeros(0, bool), backward=np.zeros(0, bool),
                            fractions=np.zeros(0, np.float32), background_forward=0.0, background_moving=False)
        assert departed_points(empty, self.OBSERVED, self.RENDERED, np.eye(4), INTR, 0.3).shape == (0, 3)

    def test_with_forget_near_the_rays_on_the_box_are_gone(self):
        kf = _keyframe([[31, 23], [5, 5]], [1.0, 3.0])  # a ray on the box, one on the wall
        pts = departed_points(self._res(), self.OBSERVED, self.RENDERED, np.eye(4), INTR, 0.3)
        assert forget_near([kf], pts, INTR, 0.05) == 1
        assert kf.gone.tolist() == [True, False] and kf.usable.tolist() == [False, True]


class TestDepartedPlaces:
    """DepartedPlaces: the cells where the check saw something leave, asked whether points lie near them."""

    def test_empty_and_near(self):
        places = DepartedPlaces()
        assert len(places) == 0 and places.near(np.zeros((3, 3)), 1.0).tolist() == [False] * 3
        places.add(np.zeros((0, 3)))
        places.add(np.array([[1.01, 1.01, 1.01], [1.02, 1.03, 1.04]]))  # one cell
        assert len(places) == 1
        centre = (np.floor(1.01 / places.CELL) + 0.5) * places.CELL
        pts = np.array([[centre, centre, centre + 0.29], [centre, centre, centre + 0.31], [5.0, 5.0, 5.0]])
        assert places.near(pts, 0.3).tolist() == [True, False, False]
        assert places.near(np.zeros((0, 3)), 0.3).shape == (0,)

    def test_state_round_trip(self):
        places = DepartedPlaces()
        places.add(np.array([[0.0, 0.0, 0.0], [-1.0, 2.0, 0.5], [3.0, 3.0, 3.0]]))
        again = DepartedPlaces()
        again.load(places.state())
        assert len(again) == 3 and np.array_equal(again.state(), places.state())
        pts = np.random.default_rng(0).uniform(-2, 4, (200, 3))
        assert np.array_equal(again.near(pts, 0.5), places.near(pts, 0.5))
        again.load(())
        assert len(again) == 0


class TestDepartedSurface:
    """departed_surface: the newest keyframe that decides about a point says whether it saw through it."""

    CAM = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5, width=64, height=48)

    def _kf(self, depth, frame_id=0):
        """A keyframe at the origin looking down +z whose whole depth map reads ``depth`` (m) everywhere
        (an (H, W) array or a number; 0 = no reading)."""
        d = np.broadcast_to(np.asarray(depth, np.float32), (48, 64))
        kf = _keyframe([[0, 0]], [1.0])
        kf.frame_id = frame_id
        kf.depth_raw_small = d[::DEPTH_STRIDE, ::DEPTH_STRIDE].astype(np.float16)
        return kf

    @staticmethod
    def _on_axis(*z):
        return np.array([[0.0, 0.0, zz] for zz in z])  # at pixel (31.5, 23.5): inside, away from the border

    def test_shape_and_no_keyframes(self):
        out = departed_surface(self._on_axis(1.0, 2.0), [], self.CAM, 0.1)
        assert out.shape == (2,) and out.dtype == bool and not out.any()
        assert departed_surface(np.zeros((0, 3)), [self._kf(2.0)], self.CAM, 0.1).shape == (0,)

    def test_seen_through_there_and_behind(self):
        # the wall at 2 m: a point at 1 m was seen through, one at 1.95 m is on the wall, one at 3 m hidden by it
        out = departed_surface(self._on_axis(1.0, 1.95, 3.0, 1.85), [self._kf(2.0)], self.CAM, 0.1)
        assert out.tolist() == [True, False, False, True]

    def test_the_newest_deciding_keyframe_wins(self):
        old_wall, new_wall = self._kf(1.0, frame_id=0), self._kf(2.0, frame_id=5)
        # the surface at 1 m was seen there first, then seen through: departed
        assert departed_surface(self._on_axis(1.0), [old_wall, new_wall], self.CAM, 0.1).tolist() == [True]
        # seen through first, then seen there (something came back): kept
        assert departed_surface(self._on_axis(1.0), [new_wall, old_wall], self.CAM, 0.1).tolist() == [False]

    def test_occluded_or_unread_leaves_it_to_older_keyframes(self):
        through = self._kf(2.0, frame_id=0)
        for newest in (self._kf(0.5, frame_id=5), self._kf(0.0, frame_id=5)):  # something in front / no depth
            assert departed_surface(self._on_axis(1.0), [through, newest], self.CAM, 0.1).tolist() == [True]
            assert not departed_surface(self._on_axis(1.0), [newest], self.CAM, 0.1).any()

    def test_a_margin_for_each_point(self):
        # the wall at 2 m: points 4 and 8 cm in front of it, each with a margin of 5 cm or of 10 cm
        pts = self._on_axis(1.96, 1.92, 1.96, 1.92)
        out = departed_surface(pts, [self._kf(2.0)], self.CAM, np.array([0.05, 0.05, 0.10, 0.10]))
        assert out.tolist() == [False, True, False, False]
        assert departed_surface(pts, [self._kf(2.0)], self.CAM, 0.05).tolist() == [False, True, False, True]

    def test_outside_the_image_is_undecided(self):
        assert not departed_surface(np.array([[5.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), [self._kf(2.0)], self.CAM, 0.1).any()

    def test_a_nearer_reading_around_the_pixel_keeps_an_edge(self):
        # a depth edge through the point's pixel: the wall at 2 m on the right, a surface at 1 m on the left
        d = np.full((48, 64), 2.0, np.float32)
        d[:, :32] = 1.0
        assert departed_surface(self._on_axis(1.0), [self._kf(d)], self.CAM, 0.1).tolist() == [False]
        assert departed_surface(self._on_axis(1.0), [self._kf(d)], self.CAM, 0.1, reach=0).tolist() == [True]
        d[:, :24] = 1.0
        d[:, 24:] = 2.0
        assert departed_surface(self._on_axis(1.0), [self._kf(d)], self.CAM, 0.1).tolist() == [True]
