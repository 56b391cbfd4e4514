import io

import numpy as np
import pytest
import torch

from dynslam_cli.errors import DynslamError
from dynslam_cli.slam.system import SLAM
from dynslam_cli.slam.toyscene import TinyIntrinsics, ToyFrame, tiny_config, trajectory

INTR = TinyIntrinsics(48, 36, f=20.0)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    torch.set_num_threads(1)  # 2 shared cores: no OpenMP spin-waiting (conftest puts the count back)


def test_state_dict_round_trip_and_resume_equality():
    cfg = tiny_config(**{"mapping.first_iters": 20, "tracking.iters": 4, "mapping.iters": 3,
                         "mapping.every": 2, "mapping.keyframe_every": 2})
    poses = trajectory(5, step=0.01)
    frames = [ToyFrame(i, p, INTR) for i, p in enumerate(poses)]
    a = SLAM(cfg, INTR, torch.device("cpu"))
    for f in frames:
        a.process(f)
    b = SLAM(cfg, INTR, torch.device("cpu"))
    for f in frames[:3]:
        b.process(f)
    buf = io.BytesIO()
    torch.save(b.state_dict(), buf)
    buf.seek(0)
    c = SLAM(cfg, INTR, torch.device("cpu"))
    c.load_state_dict(torch.load(buf, weights_only=False))
    assert len(c.keyframes) == len(b.keyframes) and np.allclose(c.trajectory(), b.trajectory())
    assert np.array_equal(c.frontend.prev_depth, b.frontend.prev_depth)
    for f in frames[3:]:
        c.process(f)
    ta, tc = a.trajectory(), c.trajectory()
    assert ta.shape == (5, 4, 4)
    assert np.array_equal(ta, tc), np.abs(ta - tc).max()  # a resumed run continues identically
    assert np.array_equal(np.array(a.online), np.array(c.online))  # and so do the poses each frame had when done


def test_online_poses_are_each_frames_pose_when_it_was_done():
    """SLAM.online: frame i's pose as map() of frame i left it; later bundle adjustments move the
    trajectory, not these."""
    cfg = tiny_config(**{"mapping.first_iters": 5, "tracking.iters": 2, "mapping.iters": 2,
                         "mapping.every": 2, "mapping.keyframe_every": 2})
    slam = SLAM(cfg, INTR, torch.device("cpu"))
    seen = []
    for i, p in enumerate(trajectory(4, step=0.01)):
        slam.process(ToyFrame(i, p, INTR))
        seen.append(slam.poses[i].copy())
    assert len(slam.online) == 4 and all(np.array_equal(a, b) for a, b in zip(slam.online, seen, strict=True))
    slam.poses[1][:3, 3] += 0.05  # as a later bundle adjustment would move it
    assert np.array_equal(slam.online[1], seen[1])  # copies: what the frame had stays
    old = slam.state_dict()
    del old["online"]  # a checkpoint from before: the earlier frames' online poses are unknown
    fresh = SLAM(cfg, INTR, torch.device("cpu"))
    fresh.load_state_dict(old)
    fresh.process(ToyFrame(4, trajectory(5, step=0.01)[4], INTR))
    assert fresh.online is None


def test_process_tracks_then_maps_each_frame():
    cfg = tiny_config(**{"mapping.first_iters": 5, "tracking.iters": 2, "mapping.iters": 2,
                         "mapping.every": 2, "mapping.keyframe_every": 2})
    slam = SLAM(cfg, INTR, torch.device("cpu"))
    poses = trajectory(3, step=0.01)
    res = [slam.process(ToyFrame(i, p, INTR)) for i, p in enumerate(poses)]
    assert [r.index for r in res] == [0, 1, 2] and [r.timestamp for r in res] == [0.0, 1.0, 2.0]
    assert np.array_equal(res[0].pose_c2w, poses[0])  # the first frame's ground truth fixes the frame
    assert res[0].map.ba and res[0].map.iters == 5 and res[0].map.keyframe and res[1].map is None
    assert res[2].map.ba and res[2].map.keyframe and [k.frame_id for k in slam.keyframes] == [0, 2]
    assert slam.n_frames == 3 and slam.trajectory().shape == (3, 4, 4) and slam.backend is None
    assert res[1].track.iters == 2 and slam.kf_of == [0, 0, 2] and slam.rel[1] is not None


def test_calls_out_of_order_and_wrong_sizes_are_user_errors():
    slam = SLAM(tiny_config(), INTR, torch.device("cpu"))
    f = ToyFrame(0, np.eye(4), INTR)
    with pytest.raises(DynslamError, match="map\\(\\) must follow track"):
        slam.map(f)
    with pytest.raises(DynslamError, match="render\\(\\) needs a map"):
        slam.render(np.eye(4))
    with pytest.raises(DynslamError, match="extract_mesh\\(\\) needs a map"):
        slam.extract_mesh(0.05)
    small = ToyFrame(0, np.eye(4), TinyIntrinsics(24, 18, f=10.0))
    with pytest.raises(DynslamError, match="does not match the intrinsics"):
        slam.track(small)
    assert slam.n_frames == 0 and slam.model is None  # nothing was built
    with pytest.raises(DynslamError, match="retrack"):
        slam.retrack(f)
