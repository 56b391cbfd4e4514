from dataclasses import replace

import numpy as np
import pytest
import torch

from dynslam_cli.errors import DynslamError
from dynslam_cli.geometry.lie import se3_exp_np
from dynslam_cli.slam import mapper
from dynslam_cli.slam.keyframes import KeyframeStore, valid_pixels
from dynslam_cli.slam.mapper import Mapper, auto_bounds
from dynslam_cli.slam.state import SlamState
from dynslam_cli.slam.system import SLAM
from dynslam_cli.slam.toyscene import BOX, TinyIntrinsics, ToyFrame, first_frame_state, load_slam, tiny_config, trajectory

INTR = TinyIntrinsics(48, 36, f=20.0)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    torch.set_num_threads(1)  # 2 shared cores: no OpenMP spin-waiting (conftest puts the count back)


@pytest.fixture(scope="module")
def fitted_state():
    """The toy scene's first frame mapped (tiny_config)."""
    return first_frame_state(tiny_config(), INTR)


def test_auto_bounds_cover_the_first_frame_and_the_camera():
    f = ToyFrame(0, np.eye(4), INTR)
    b = auto_bounds(f, INTR, np.eye(4), 0.0)
    assert b.shape == (2, 3) and np.all(b[0] <= 0) and np.all(b[1] >= 0)  # the camera is inside
    assert np.all(b[0] >= BOX[0] - 1e-4) and np.all(b[1] <= BOX[1] + 1e-4)  # the points are inside the box
    assert b[1, 2] == pytest.approx(BOX[1, 2], abs=1e-4)  # the back wall is seen
    assert np.allclose(auto_bounds(f, INTR, np.eye(4), 0.5), b + [[-0.5], [0.5]])
    f.depth = np.zeros_like(f.depth)
    with pytest.raises(DynslamError, match="map bounds"):
        auto_bounds(f, INTR, np.eye(4), 0.0)


def _concatenated_rays(state):
    """The keyframe rays as the mapper once cached them: everything concatenated up front."""
    uv = np.concatenate([k.pixels for k in state.keyframes])
    flat = torch.from_numpy(uv[:, 1].astype(np.int64) * state.W + uv[:, 0])
    return {"dirs": state.dirs[flat], "rgb": state.t(np.concatenate([k.rgb for k in state.keyframes])) / 255.0,
            "depth": state.t(np.concatenate([k.depth for k in state.keyframes])),
            "owner": torch.from_numpy(np.concatenate([np.full(len(k), i) for i, k in enumerate(state.keyframes)]))}


def test_keyframes_store_a_fraction_of_the_pixels_and_their_rays_are_gathered_as_concatenated():
    state = SlamState(tiny_config(), INTR, torch.device("cpu"))
    m = Mapper(state)
    m.build_model(np.array(tiny_config().map.bounds))
    assert state.model is not None and state.map_opt is not None and m.keyframe_rays(np.arange(3)) is None
    for i in range(3):
        cur = state.prepare(ToyFrame(i, se3_exp_np(np.array([0.0, 0.0, 0.0, 0.02 * i, 0.01 * i, 0.0])), INTR), None)
        state.poses.append(np.eye(4))  # tracked
        kf = m.add_keyframe(cur, None)
    n = round(state.cfg.mapping.keyframe_ray_fraction * INTR.width * INTR.height)
    assert len(kf) == n and kf.frame_id == 2 and np.all(kf.instance_ids == -1) and kf.usable.all()
    short = state.keyframes[1]  # keyframes of other lengths (one empty) in between
    frames = list(state.keyframes)
    frames[1:1] = [replace(short, pixels=short.pixels[:7], rgb=short.rgb[:7], depth=short.depth[:7]),
                   replace(short, pixels=short.pixels[:0], rgb=short.rgb[:0], depth=short.depth[:0])]
    state.keyframes = KeyframeStore()
    for k in frames:
        state.keyframes.add(k)
    ref = _concatenated_rays(state)
    total = 3 * n + 7
    assert ref["owner"].tolist() == [0] * n + [1] * 7 + [3] * n + [4] * n
    for idx in (np.arange(total), np.random.default_rng(0).integers(0, total, 500), np.zeros(0, np.int64)):
        rays = m.keyframe_rays(idx)
        assert rays["n"] == 5 and rays["dirs"].shape == (len(idx), 3) and rays["depth"].shape == (len(idx),)
        t = torch.from_numpy(idx)
        for key in ("dirs", "rgb", "depth", "owner"):  # the same values, bit for bit, and types
            assert rays[key].dtype == ref[key].dtype and torch.equal(rays[key], ref[key][t]), key
    assert float(m.keyframe_rays(np.arange(total))["rgb"].max()) <= 1.0
    with pytest.raises(IndexError):
        m.keyframe_rays(np.array([total]))


def test_sampling_respects_masks_and_keyframe_usable_flags():
    cfg = tiny_config(**{"mapping.first_iters": 2})
    slam = SLAM(cfg, INTR, torch.device("cpu"))
    f0 = ToyFrame(0, np.eye(4), INTR)
    mask = np.ones((INTR.height, INTR.width), bool)
    mask[:, : INTR.width // 2] = False
    ids = np.arange(INTR.height * INTR.width, dtype=np.int32).reshape(INTR.height, INTR.width)
    slam.track(f0, mask)
    valid = valid_pixels(f0.depth, mask, cfg.tracking.ignore_border)
    assert np.all(mask.reshape(-1)[slam.sample(valid, 5000)])
    slam.map(f0, mask, instance_ids=ids)
    kf = slam.keyframes[0]
    flat = kf.pixels[:, 1] * INTR.width + kf.pixels[:, 0]
    assert np.array_equal(kf.usable, mask.reshape(-1)[flat]) and kf.usable.any() and not kf.usable.all()
    assert np.array_equal(kf.instance_ids, flat.astype(np.int32))
    cur = slam.prepare(ToyFrame(1, np.eye(4), INTR), mask)
    kfi, curi = slam.mapper.ba_ray_indices(cur, 4, 400)
    assert len(kfi) and np.all(kf.usable[kfi]) and np.all(mask.reshape(-1)[curi])
    kf.usable[:] = False  # the dynamic module forgets every stored ray
    kfi, curi = slam.ba_ray_indices(cur, 4, 400)
    assert len(kfi) == 0 and len(curi) == 4 * 400


def test_keyframe_rays_stay_off_depth_edges():
    intr = TinyIntrinsics(48, 36, f=60.0)  # a narrow view: the box walls themselves are no edges
    slam = SLAM(tiny_config(**{"mapping.first_iters": 2}), intr, torch.device("cpu"))
    f = ToyFrame(0, np.eye(4), intr)
    f.depth[:, 24:] *= 0.25  # a depth discontinuity at column 24
    slam.process(f)
    assert not np.isin(slam.keyframes[0].pixels[:, 0], np.arange(21, 27)).any()


@pytest.mark.parametrize("iters,accum,steps", [(20, 5, 4), (7, 5, 2), (6, 1, 6)])
def test_bundle_adjustment_steps_poses_once_per_accumulation(fitted_state, monkeypatch, iters, accum, steps):
    state = fitted_state
    monkeypatch.setattr(mapper, "POSE_ACCUM_STEPS", accum)
    slam = load_slam(tiny_config(**{"mapping.iters": iters, "mapping.every": 1}), INTR, state)
    pose_steps = []
    orig = mapper.Adam.step

    def spy(self, *a, **k):
        if any(p.dim() == 2 and p.shape[-1] == 6 for p in self.params):
            pose_steps.append(1)
        return orig(self, *a, **k)

    monkeypatch.setattr(mapper.Adam, "step", spy)
    before = slam.poses[0].copy()
    res = slam.process(ToyFrame(1, se3_exp_np([0.01, 0, 0, 0, 0, 0]), INTR))
    assert res.map is not None and res.map.ba and len(pose_steps) == steps
    assert np.allclose(slam.poses[0], before)  # the first keyframe stays fixed


@pytest.mark.parametrize("lr,backend", [(0.001, False), (0.0, False), (0.001, True)])
def test_bundle_adjustment_moves_poses_only_without_the_backend_and_with_lr_pose(fitted_state, monkeypatch, lr, backend):
    state = fitted_state
    slam = load_slam(tiny_config(**{"mapping.lr_pose": lr}), INTR, state)
    seen = []
    real_adam = mapper.Adam
    monkeypatch.setattr(mapper, "Adam", lambda params, lr, **kw: seen.append(lr) or real_adam(params, lr=lr, **kw))
    f1 = ToyFrame(1, se3_exp_np([0.01, 0.0, 0.0, 0.0, 0.0, 0.0]), INTR)
    slam.track(f1)
    slam.map(f1)  # not due: nothing optimised
    if backend:
        slam.backend = object()  # poses from a backend: bundle adjustment trains the map only
    slam.mapper.optimize(slam.cur, 2, 64, first=False)
    assert (lr in seen) == (lr > 0 and not backend)  # the pose optimiser runs with lr_pose, or not at all


def test_final_bundle_adjustment_refines_keyframes_but_not_the_first(fitted_state):
    # mapping.final_iters: SLAM.finish() runs bundle adjustment after the last frame
    state = fitted_state

    def load(**over):
        return load_slam(tiny_config(**{"tracking.icp_init": False, "mapping.every": 100,
                                        "mapping.keyframe_every": 1, **over}), INTR, state)

    poses = trajectory(3, step=0.01)
    off, on = load(), load(**{"mapping.final_iters": 10})
    for s in (off, on):
        for i in (1, 2):
            s.process(ToyFrame(i, poses[i], INTR))
    assert off.finish() is None
    before = on.trajectory()
    assert np.allclose(before, off.trajectory())
    res = on.finish()
    assert res is not None and res.ba and res.iters == 10 and np.isfinite(res.loss)
    after = on.trajectory()
    assert np.allclose(after[0], before[0])  # the first keyframe stays fixed
    assert not np.allclose(after[1], before[1])
    assert np.allclose(on.keyframes[1].pose_c2w, after[1])
