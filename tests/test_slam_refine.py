"""The final bundle adjustment after the last frame (mapping.final_iters, SLAM.finish)."""

import numpy as np
import pytest
import torch

from dynslam_cli.slam.system import SLAM
from dynslam_cli.slam.toyscene import TinyIntrinsics, render, tiny_config, trajectory


class F:
    def __init__(self, i, pose, intr):
        self.index, self.timestamp = i, float(i)
        self.rgb, self.depth = render(pose, intr)
        self.pose_c2w = pose


INTR = TinyIntrinsics(48, 36, f=20.0)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def fitted():
    torch.manual_seed(0)
    cfg = tiny_config(**{"mapping.first_iters": 60})
    slam = SLAM(cfg, INTR, torch.device("cpu"))
    slam.process(F(0, np.eye(4), INTR))
    return slam.state_dict()


def _load(state, **over):
    s = SLAM(tiny_config(**{"mapping.first_iters": 60, "tracking.icp_init": False, **over}), INTR, torch.device("cpu"))
    s.load_state_dict(state)
    return s


def test_final_bundle_adjustment_refines_keyframes_but_not_the_first(fitted):
    over = {"mapping.every": 100, "mapping.keyframe_every": 1}
    poses = trajectory(3, step=0.01)
    off = _load(fitted, **over)
    on = _load(fitted, **over, **{"mapping.final_iters": 10})
    for s in (off, on):
        for i in (1, 2):
            s.process(F(i, poses[i], INTR))
    assert off.finish() is None
    before = on.trajectory()
    assert np.allclose(before, off.trajectory())
    res = on.finish()
    assert res is not None and res.ba and res.iters == 10 and np.isfinite(res.loss)
    after = on.trajectory()
    assert np.allclose(after[0], before[0])  # the first keyframe stays fixed
    assert not np.allclose(after[1], before[1])
    assert np.allclose(on.keyframes[1].pose_c2w, after[1])
