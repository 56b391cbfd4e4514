"""motion/stayed.py: instances that stayed put where the recent keyframes saw them."""

from types import SimpleNamespace

import numpy as np

from dynslam_cli.motion.stayed import RATE_FRAMES, stationary_instances, stayed_put, window_frames
from dynslam_cli.slam.keyframes import subsample_depth

INTR = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)


def test_stationary_instances_know_what_stayed_put():
    intr = INTR
    wall = np.full((48, 64), 3.0, np.float32)
    ids = np.zeros((48, 64), np.int32)
    ids[10:30, 10:25] = 1  # a box that has stood here all along
    ids[10:30, 40:55] = 2  # a box that just arrived
    now = wall.copy()
    now[10:30, 10:25] = 1.5
    now[10:30, 40:55] = 1.5
    before = wall.copy()
    before[10:30, 10:25] = 1.5  # the keyframes saw box 1 but only the wall where box 2 now is
    kfs = [SimpleNamespace(pose_c2w=np.eye(4), depth_raw_small=subsample_depth(before)) for _ in range(2)]
    assert stationary_instances(now, ids, np.eye(4), intr, kfs).tolist() == [True, False]
    assert not stationary_instances(now, ids, np.eye(4), intr, kfs[:1]).any()  # one keyframe is not enough
    gone = [SimpleNamespace(pose_c2w=np.eye(4), depth_raw_small=subsample_depth(wall)), kfs[0]]
    assert stationary_instances(now, ids, np.eye(4), intr, gone).tolist() == [False, False]
    # a keyframe that did not look there (no valid depth) neither confirms nor refutes ...
    blind = SimpleNamespace(pose_c2w=np.eye(4), depth_raw_small=subsample_depth(np.zeros_like(wall)))
    assert stationary_instances(now, ids, np.eye(4), intr, [blind] + kfs).tolist() == [True, False]
    # ... nor counts among the two that must have looked
    assert not stationary_instances(now, ids, np.eye(4), intr, [blind, kfs[0]]).any()
    turned = np.array([[0.0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]])  # looking along +x
    aside = SimpleNamespace(pose_c2w=turned, depth_raw_small=subsample_depth(wall))
    assert stationary_instances(now, ids, np.eye(4), intr, kfs + [aside]).tolist() == [True, False]
    # a keyframe that saw something in front of box 1 (a passer-by) did not look at it either
    passer = before.copy()
    passer[5:35, 5:30] = 0.8
    hidden = SimpleNamespace(pose_c2w=np.eye(4), depth_raw_small=subsample_depth(passer))
    assert stationary_instances(now, ids, np.eye(4), intr, kfs + [hidden]).tolist() == [True, False]
    assert not stationary_instances(now, ids, np.eye(4), intr, [hidden, kfs[0]]).any()


def test_stayed_put_window_and_tolerance_with_and_without_the_centre_feature():
    depth = np.full((48, 64), 1.5, np.float32)
    ids = np.ones((48, 64), np.int32)
    kfs = [SimpleNamespace(frame_id=i, pose_c2w=np.eye(4), depth_raw_small=subsample_depth(depth)) for i in (2, 4)]

    def stayed(d, centre, tol=0.0, frames=10):  # seen from frame 5, t_d 0.3 m
        return stayed_put(d, ids, np.eye(4), INTR, kfs, 5, frames, tol, 0.3, centre)

    # the stayed-put test applies with and without the centre feature; a window of 0 frames turns it off
    assert stayed(depth, False).tolist() == [True]
    assert stayed(depth, True).tolist() == [True]
    assert stayed(depth, False, frames=0) is None
    # run.still_tolerance: 10 cm closer than the keyframes saw is 'stayed put' within t_d (0 = 0.3 m)
    # but not within 5 cm, with or without the centre feature
    closer = depth - 0.1
    assert stayed(closer, False).tolist() == [True]
    assert stayed(closer, False, 0.05).tolist() == [False]
    assert stayed(closer, True, 0.05).tolist() == [False]
    assert stayed(closer, False, 0.15).tolist() == [True]
    # the window: the keyframes of frames 2 and 4 seen from frame 5; over the last 2 frames only one
    assert stayed(depth, False, frames=2).tolist() == [False]
    # with the centre feature the window is half as long: 4 frames see one keyframe, 3 frames too few to judge
    assert stayed(depth, False, frames=4).tolist() == [True]
    assert stayed(depth, True, frames=4).tolist() == [False]
    assert stayed(depth, True, frames=3) is None


class TestWindowFrames:
    """run.still_seconds in frames at the sequence's frame rate."""

    def test_known_values(self):
        assert window_frames(0.67, np.arange(40) / 30.0) == 20
        assert window_frames(0.67, np.arange(40) / 15.0) == 10  # every second frame of the same camera
        assert window_frames(0.67, np.arange(40) / 60.0) == 40

    def test_jittered_stamps_and_a_dropped_frame(self):
        rng = np.random.default_rng(0)
        stamps = np.cumsum(1 / 30.0 + rng.uniform(-0.002, 0.002, 40))
        stamps = np.delete(stamps, 20)  # a dropped frame: the median interval stays the rate's
        assert window_frames(0.67, stamps) == 20

    def test_off_and_before_two_frames(self):
        assert window_frames(0.0, np.arange(40) / 30.0) == 0
        assert window_frames(0.67, [0.5]) == 0 and window_frames(0.67, []) == 0
        assert window_frames(0.67, [1.0, 1.0]) == 0  # no interval: no rate

    def test_the_rate_follows_the_last_frames(self):
        stamps = np.concatenate([np.arange(100) / 15.0, 100 / 15.0 + np.arange(1, RATE_FRAMES + 1) / 30.0])
        assert window_frames(0.67, stamps) == 20
