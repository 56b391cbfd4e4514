import numpy as np
import pytest

from dynslam_cli.slam.keyframes import depth_edges


def test_depth_edges_mark_both_sides_of_a_step_and_holes():
    d = np.full((10, 12), 2.0, np.float32)
    d[:, 6:] = 1.0
    d[8, 1] = 0.0
    e = depth_edges(d, 0.05, 0)
    assert e[:, 5].all() and e[:, 6].all() and not e[:, 3].any() and not e[:, 9].any()
    assert e[7, 1] and e[8, 0] and not e[8, 1]  # the hole's valid neighbours, not the hole itself
    assert depth_edges(d, 0.05, 2)[:, 3:9].all()
    assert not depth_edges(np.full((5, 5), 2.0, np.float32), 0.05, 2).any()


def _depth_edges_numpy(depth, rel_jump, dilate):
    """The numpy expression the kernel replaced (the reference it must match bit for bit)."""
    import cv2

    d = np.asarray(depth, np.float32)
    valid = d > 0
    pad = np.pad(d, 1, mode="edge")
    jump = np.zeros_like(valid)
    for dy, dx in ((0, 1), (1, 0), (1, 2), (2, 1)):
        nb = pad[dy:dy + d.shape[0], dx:dx + d.shape[1]]
        jump |= (np.abs(nb - d) > rel_jump * np.maximum(d, nb)) & (nb > 0) & valid
        jump |= valid & (nb <= 0)
    k = 2 * int(dilate) + 1
    return jump if dilate <= 0 else cv2.dilate(jump.astype(np.uint8), np.ones((k, k), np.uint8)) > 0


def test_depth_edges_match_the_numpy_expression_bit_for_bit():
    rng = np.random.default_rng(0)
    # depths c whose step to c / 0.95 is 5 % of the larger exactly, in float32: columns alternating
    # between the two sit on the threshold everywhere, where the comparison and the rounding decide
    c = (rng.random(2000) * 4 + 0.3).astype(np.float32)
    far = (c / np.float32(0.95)).astype(np.float32)
    tie = np.abs(far - c) == np.float32(0.05) * far
    c, far = c[tie], far[tie]
    assert len(c) > 10
    for t in range(40):
        h, w = rng.integers(1, 40, 2)
        d = (rng.random((h, w)) * 4).astype(np.float32)
        d[rng.random(d.shape) < 0.2] = 0.0
        d[rng.random(d.shape) < 0.05] = np.nan
        if t % 2:
            d = np.where(np.arange(w) % 2 == 1, far[t], c[t]).astype(np.float32)[None].repeat(h, 0)
        for rel, dil in ((0.05, 0), (0.05, 2), (0.3, 1), (0.0499, 3)):
            np.testing.assert_array_equal(depth_edges(d, rel, dil), _depth_edges_numpy(d, rel, dil))


def _kf(fid, n, start=0):
    from dynslam_cli.slam.keyframes import Keyframe

    px = np.stack([np.arange(start, start + n), np.full(n, fid)], 1).astype(np.int32)
    return Keyframe(fid, float(fid), px, np.full((n, 3), fid, np.uint8), np.arange(n, dtype=np.float32) + fid,
                    np.arange(n, dtype=np.int32), np.ones(n, bool))


class TestKeyframeStore:
    def _store(self):
        from dynslam_cli.slam.keyframes import KeyframeStore

        store = KeyframeStore()
        store.add(_kf(0, 3))
        store.add(_kf(5, 2, start=10))
        return store

    def test_sequence_of_keyframes(self):
        store = self._store()
        assert len(store) == 2 and store[-1].frame_id == 5 and [k.frame_id for k in store] == [0, 5]
        assert [k.frame_id for k in store[-1:]] == [5]

    def test_gather_known_rays_in_any_order(self):
        store = self._store()
        uv, rgb, depth, owner = store.gather(np.array([4, 0, 3, 2]))
        assert owner.tolist() == [1, 0, 1, 0]
        assert uv.tolist() == [[11, 5], [0, 0], [10, 5], [2, 0]]
        assert rgb[:, 0].tolist() == [5, 0, 5, 0] and depth.tolist() == [6.0, 0.0, 5.0, 2.0]
        with pytest.raises(IndexError):
            store.gather(np.array([5]))

    def test_usable_rays(self):
        store = self._store()
        store[0].usable[1] = False
        assert store.usable_rays().tolist() == [0, 2, 3, 4]

    def test_forget_without_a_backend_and_a_state_round_trip(self):
        from dynslam_cli.slam.keyframes import KeyframeStore

        store = self._store()
        store.register_instances(5, np.ones((2, 4)), np.array([False, True]))
        assert store.has_instances(5) and not store.has_instances(0)
        assert store.forget({5: np.array([1])}) == 1  # ray of instance 1 in keyframe 5
        assert store[1].usable.tolist() == [True, False] and store[0].usable.all()
        back = KeyframeStore()
        back.load_state_dict(store.state_dict())
        assert [k.frame_id for k in back] == [0, 5] and back[1].usable.tolist() == [True, False]
        rec = back.instances()[5]
        assert rec["feats"].dtype == np.float32 and rec["prior"].tolist() == [False, True]

    def test_forget_reaches_the_backend_keyframes_landmarks_and_they_round_trip(self):
        from dynslam_cli.backend.features import Keypoints
        from dynslam_cli.slam.keyframes import KeyframeStore

        store = self._store()
        lkf = store.landmark_keyframes
        k = lkf.add(5, np.eye(4))
        n = 3
        kp = Keypoints(uv=np.zeros((n, 2)), des=np.zeros((n, 32), np.uint8), depth=np.ones(n),
                       octave=np.zeros(n, np.int64), dsig=np.full(n, 0.01))
        lkf.landmarks.create(k, kp, np.ones((n, 3)), np.zeros(3), np.array([1, 2, 1]))
        store.register_instances(5, np.ones((2, 4)), np.array([False, False]))
        store.forget({5: np.array([1])})
        assert lkf.landmarks.moving.tolist() == [True, False, True]  # the landmarks made on instance 1
        back = KeyframeStore()
        held = back.landmark_keyframes  # a backend made before loading keeps working on the loaded state
        back.load_state_dict(store.state_dict())
        assert back.landmark_keyframes is held and held.frames.tolist() == [5]
        assert held.landmarks.moving.tolist() == [True, False, True]
