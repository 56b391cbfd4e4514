import numpy as np
import pytest
import torch

from dynslam_cli.slam.keyframes import Keyframe
from dynslam_cli.slam.render import RENDER_BLOCK, _first_crossing, observed_points, render_view
from dynslam_cli.slam.toyscene import TinyIntrinsics, ToyFrame, first_frame_state, load_slam, render, tiny_config

INTR = TinyIntrinsics(48, 36, f=20.0)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    torch.set_num_threads(1)  # 2 shared cores: no OpenMP spin-waiting (conftest puts the count back)


def test_fitted_map_renders_the_right_depth():
    cfg = tiny_config()
    slam = load_slam(cfg, INTR, first_frame_state(cfg, INTR))
    depth, rgb = render_view(slam.model, cfg.map, INTR, np.eye(4), 0.5, torch.device("cpu"))
    _, gt = render(np.eye(4), TinyIntrinsics(24, 18, f=INTR.fx / 2))
    assert depth.shape == (18, 24) and rgb.shape == (18, 24, 3) and rgb.dtype == np.uint8
    err = np.abs(depth - gt)[3:-3, 3:-3]
    assert np.median(err) < 0.05, np.median(err)
    d2, rgb2 = slam.render(np.eye(4), scale=0.5)  # SLAM.render is this view
    assert np.array_equal(d2, depth) and np.array_equal(rgb2, rgb)


class _Slabs:
    """An SDF (truncation units) of slabs along z: negative inside [z0, z1] of any slab, positive outside."""

    def __init__(self, slabs):
        self.slabs = slabs

    def __call__(self, pts, color=False):
        z = pts[:, 2]
        s = torch.ones_like(z)
        for z0, z1 in self.slabs:
            s = torch.minimum(s, torch.maximum(z0 - z, z - z1))
        return s, None


class TestFirstCrossing:
    @pytest.mark.parametrize("slabs", [[(1.0, 1.3)], [(0.4, 0.5), (2.0, 4.0)], [(3.9, 6.0)], []])
    def test_equals_evaluating_every_sample(self, slabs):
        """Blocks near to far on the rays still open give the first crossing of the full sweep, for
        crossings inside a block, across a block boundary, late and none."""
        model = _Slabs(slabs)
        zc = 0.1 + (torch.arange(32, dtype=torch.float32) + 0.5) / 32 * 4.9
        d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.1, 1.0], [-0.5, 0.2, 1.0]]), dim=1)
        o = torch.zeros(1, 3)
        j, s0, s1, has = _first_crossing(model, o, d, zc)
        s = model((o[:, None, :] + d[:, None, :] * zc[None, :, None]).reshape(-1, 3))[0].view(3, 32)
        cross = (s[:, :-1] > 0) & (s[:, 1:] <= 0)
        assert torch.equal(has, cross.any(1))
        jr = cross.float().argmax(1)
        assert torch.equal(j[has], jr[has]) and torch.all(j[~has] == 0)
        assert torch.equal(s0[has], s[has, jr[has]]) and torch.equal(s1[has], s[has, jr[has] + 1])
        if slabs == [(3.9, 6.0)]:
            assert has.all() and (j >= RENDER_BLOCK).all()  # found in a later block


def _keyframe(frame_id, pose, n):
    f = ToyFrame(frame_id, pose, INTR)
    uv = np.stack([np.arange(n) % INTR.width, np.arange(n) // INTR.width], 1).astype(np.int32)
    depth = f.depth[uv[:, 1], uv[:, 0]]
    return Keyframe(frame_id, float(frame_id), uv, f.rgb[uv[:, 1], uv[:, 0]], depth, np.zeros(n, np.int32),
                    np.ones(n, bool), pose, None), depth


def test_observed_points_are_the_keyframes_depth_in_the_world():
    assert observed_points([], INTR).shape == (0, 3)
    pose = np.eye(4)
    pose[:3, 3] = [0.1, 0.0, 0.2]
    kf, depth = _keyframe(0, pose, 100)
    pts = observed_points([kf, _keyframe(1, np.eye(4), 50)[0]], INTR)
    assert pts.shape == (150, 3)
    assert np.allclose(pts[:100, 2], depth + 0.2, atol=1e-5)  # camera z plus the pose's offset
    sub = observed_points([kf], INTR, max_points=10)
    assert sub.shape == (10, 3) and np.array_equal(sub, observed_points([kf], INTR, max_points=10))
    assert all(any(np.allclose(p, q) for q in pts[:100]) for p in sub)
