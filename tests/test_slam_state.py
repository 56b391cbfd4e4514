import numpy as np
import pytest
import torch

from dynslam_cli.errors import DynslamError
from dynslam_cli.geometry.lie import se3_exp_np
from dynslam_cli.slam.state import MIN_PIXELS, SlamState
from dynslam_cli.slam.toyscene import TinyIntrinsics, ToyFrame, tiny_config

INTR = TinyIntrinsics(48, 36, f=20.0)


def _state(intr=INTR):
    return SlamState(tiny_config(), intr, torch.device("cpu"))


def test_prepare_checks_the_size_and_keeps_usable_pixels():
    s = _state()
    f = ToyFrame(0, np.eye(4), INTR)
    f.depth[0:5, 10:20] = np.nan
    mask = np.ones((INTR.height, INTR.width), bool)
    mask[:, :10] = False
    cur = s.prepare(f, mask)
    assert cur.idx == 0 and cur.rgb.shape == (INTR.width * INTR.height, 3) and float(cur.rgb.max()) <= 1.0
    assert np.all(np.isfinite(cur.depth_np)) and not cur.depth_np[0:5, 10:20].any()
    assert np.all(mask.reshape(-1)[cur.valid]) and np.all(cur.depth_np.reshape(-1)[cur.valid] > 0)
    assert np.all(mask.reshape(-1)[s.sample(cur.valid, 1000)])
    assert not cur.masked_depth()[:, :10].any() and cur.masked_depth()[10:20, 20:30].all()
    f.depth = f.depth[:, :-1]
    with pytest.raises(DynslamError, match="does not match the intrinsics 36x48"):
        s.prepare(f, None)


def test_without_edges_drops_pixels_near_a_depth_step():
    intr = TinyIntrinsics(48, 36, f=60.0)  # a narrow view: the box walls themselves are no edges
    f = ToyFrame(0, np.eye(4), intr)
    f.depth[:, 24:] *= 0.25  # a depth discontinuity at column 24
    cur = _state(intr).prepare(f, None)
    kept = cur.without_edges(cur.valid, 2, intr.fx)
    cols = kept % intr.width
    assert len(kept) < len(cur.valid) and not np.isin(cols, np.arange(21, 27)).any()
    assert np.isin(np.arange(3, 18), np.unique(cols)).all()  # the rest of the frame is kept
    assert np.array_equal(cur.without_edges(cur.valid, 0, intr.fx), cur.valid)
    few = cur.valid[np.isin(cur.valid % intr.width, [23, 24])][: MIN_PIXELS + 5]  # all edge pixels
    assert np.array_equal(cur.without_edges(few, 2, intr.fx), few)  # too few would be left: all kept
    assert not cur.icp_depth(intr.fx)[:, 21:27].any() and cur.icp_depth(intr.fx)[:, 5:15].all()


def test_pose_of_follows_the_keyframe_and_events_are_logged():
    s = _state()
    kf, rel = se3_exp_np([0.1, 0, 0, 0, 0.1, 0]), se3_exp_np([0.0, 0.02, 0, 0, 0, 0])
    s.poses, s.rel, s.kf_of = [kf, kf @ rel], [None, rel], [0, 0]
    moved = se3_exp_np([0.0, 0.0, 0.05, 0, 0, 0]) @ kf
    s.poses[0] = moved  # bundle adjustment refined the keyframe
    assert np.allclose(s.pose_of(1), moved @ rel) and np.allclose(s.pose_of(0), moved) and s.n_frames == 2
    s.event(1, "lost", "too few matches")
    assert s.events == [{"frame": 1, "kind": "lost", "detail": "too few matches"}]


def test_the_backend_weighs_depth_by_the_sequences_noise():
    from dynslam_cli.data.config import DataConfig

    cfg = tiny_config(**{"tracking.backend": True})
    s = SlamState(cfg, INTR, torch.device("cpu"), depth_noise=0.002)
    be = s.make_backend()
    assert be.detector.depth_noise == 0.002
    assert be.keyframes is s.keyframes.landmark_keyframes  # forgetting reaches its landmarks through the store
    assert SlamState(cfg, INTR, torch.device("cpu")).make_backend().detector.depth_noise == DataConfig.DEPTH_NOISE
