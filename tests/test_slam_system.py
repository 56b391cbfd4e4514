import io

import numpy as np
import pytest
import torch

from dynslam_cli.geometry.lie import se3_exp_np
from dynslam_cli.slam.keyframes import depth_edges, valid_pixels
from dynslam_cli.slam.system import SLAM
from dynslam_cli.slam.toyscene import TinyIntrinsics, render, tiny_config, trajectory


class F:
    def __init__(self, i, pose, intr, with_gt=True):
        self.index, self.timestamp = i, float(i)
        self.rgb, self.depth = render(pose, intr)
        self.pose_c2w = pose if with_gt else None


INTR = TinyIntrinsics(48, 36, f=20.0)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # 2 shared cores: one intra-op thread avoids OpenMP spin-waiting under load (10x faster here)
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def fitted():
    torch.manual_seed(0)
    cfg = tiny_config()
    slam = SLAM(cfg, INTR, torch.device("cpu"))
    slam.process(F(0, np.eye(4), INTR))
    return cfg, slam.state_dict()


def _load(cfg, state):
    s = SLAM(cfg, INTR, torch.device("cpu"))
    s.load_state_dict(state)
    return s


def test_fitted_map_renders_the_right_depth(fitted):
    cfg, state = fitted
    slam = _load(cfg, state)
    depth, rgb = slam.render(np.eye(4), scale=0.5)
    _, gt = render(np.eye(4), TinyIntrinsics(24, 18, f=INTR.fx / 2))
    assert depth.shape == (18, 24) and rgb.shape == (18, 24, 3) and rgb.dtype == np.uint8
    err = np.abs(depth - gt)[3:-3, 3:-3]
    assert np.median(err) < 0.05, np.median(err)


def test_tracking_recovers_a_small_perturbation(fitted):
    cfg, state = fitted
    slam = _load(cfg, state)
    true = se3_exp_np([0.03, -0.02, 0.02, 0.01, -0.015, 0.01])
    res = slam.track(F(1, true, INTR))
    assert not res.diverged and res.iters == cfg.tracking.iters
    before = np.linalg.norm(true[:3, 3])
    after = np.linalg.norm(res.pose_c2w[:3, 3] - true[:3, 3])
    assert after < 0.5 * before, (before, after)


def test_divergence_falls_back_to_the_constant_velocity_pose(fitted, monkeypatch):
    import dynslam_cli.slam.system as system

    cfg, state = fitted
    monkeypatch.setattr(system, "MAX_JUMP", 1e-9)
    slam = _load(cfg, state)
    res = slam.track(F(1, se3_exp_np([0.03, 0, 0, 0, 0, 0]), INTR))
    assert res.diverged and "jump" in res.reason
    assert np.allclose(res.pose_c2w, np.eye(4)) and slam.events[-1]["frame"] == 1
    slam2 = _load(cfg, state)
    slam2.model.query = lambda pts, color=True, grid_extra=None: (
        torch.full((len(pts),), float("nan")), torch.zeros(len(pts), 3), None)
    res2 = slam2.track(F(1, np.eye(4), INTR))
    assert res2.diverged and "non-finite" in res2.reason and np.all(np.isfinite(res2.pose_c2w))
    monkeypatch.undo()


def test_sampling_respects_masks_and_keyframe_usable_flags():
    cfg = tiny_config(**{"mapping.first_iters": 2})
    slam = SLAM(cfg, INTR, torch.device("cpu"))
    f0 = F(0, np.eye(4), INTR)
    mask = np.ones((INTR.height, INTR.width), bool)
    mask[:, : INTR.width // 2] = False
    ids = np.arange(INTR.height * INTR.width, dtype=np.int32).reshape(INTR.height, INTR.width)
    slam.track(f0, mask)
    valid = valid_pixels(f0.depth, mask, cfg.tracking.ignore_border)
    assert np.all(mask.reshape(-1)[slam._sample(valid, 5000)])
    slam.map(f0, mask, instance_ids=ids)
    kf = slam.keyframes[0]
    flat = kf.pixels[:, 1] * INTR.width + kf.pixels[:, 0]
    assert np.array_equal(kf.usable, mask.reshape(-1)[flat]) and kf.usable.any() and not kf.usable.all()
    assert np.array_equal(kf.instance_ids, flat.astype(np.int32))
    cur = slam._prepare(F(1, np.eye(4), INTR), mask)
    kfi, curi = slam.ba_ray_indices(cur, 4, 400)
    assert len(kfi) and np.all(kf.usable[kfi]) and np.all(mask.reshape(-1)[curi])
    kf.usable[:] = False  # the dynamic module forgets every stored ray
    kfi, curi = slam.ba_ray_indices(cur, 4, 400)
    assert len(kfi) == 0 and len(curi) == 4 * 400


def test_state_dict_round_trip_and_resume_equality():
    cfg = tiny_config(**{"mapping.first_iters": 20, "tracking.iters": 4, "mapping.iters": 3,
                         "mapping.every": 2, "mapping.keyframe_every": 2})
    poses = trajectory(5, step=0.01)
    frames = [F(i, p, INTR) for i, p in enumerate(poses)]
    torch.manual_seed(0)
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
    for f in frames[3:]:
        c.process(f)
    ta, tc = a.trajectory(), c.trajectory()
    assert ta.shape == (5, 4, 4)
    assert np.allclose(ta, tc, atol=1e-6), np.abs(ta - tc).max()


def _stepped(f):
    """A toy frame whose right half is four times closer: a depth discontinuity at column 24."""
    f.depth = f.depth.copy()
    f.depth[:, 24:] *= 0.25
    return f


def test_depth_edges_mark_both_sides_of_a_step_and_holes():
    d = np.full((10, 12), 2.0, np.float32)
    d[:, 6:] = 1.0
    d[8, 1] = 0.0
    e = depth_edges(d, 0.05, 0)
    assert e[:, 5].all() and e[:, 6].all() and not e[:, 3].any() and not e[:, 9].any()
    assert e[7, 1] and e[8, 0] and not e[8, 1]  # the hole's valid neighbours, not the hole itself
    assert depth_edges(d, 0.05, 2)[:, 3:9].all()
    assert not depth_edges(np.full((5, 5), 2.0, np.float32), 0.05, 2).any()


def test_edge_margin_keeps_tracking_and_keyframe_rays_off_depth_edges():
    cfg = tiny_config(**{"mapping.first_iters": 2})
    intr = TinyIntrinsics(48, 36, f=60.0)  # a narrow view: the box walls themselves are no edges
    slam = SLAM(cfg, intr, torch.device("cpu"))
    f = _stepped(F(0, np.eye(4), intr))
    slam.track(f)
    cur = slam._cur
    kept = slam._without_edges(cur, cur.valid, 2)
    cols = kept % intr.width
    assert len(kept) < len(cur.valid) and not np.isin(cols, np.arange(21, 27)).any()
    assert np.isin(np.arange(3, 18), np.unique(cols)).all()  # the rest of the frame is kept
    slam.map(f)
    assert not np.isin(slam.keyframes[0].pixels[:, 0], np.arange(21, 27)).any()
    off = SLAM(tiny_config(**{"mapping.first_iters": 2}), intr, torch.device("cpu"))
    off.track(f)
    assert np.array_equal(off._without_edges(off._cur, off._cur.valid, 0), off._cur.valid)


@pytest.mark.parametrize("iters,accum,steps", [(20, 5, 4), (7, 5, 2), (6, 1, 6)])
def test_bundle_adjustment_steps_poses_once_per_accumulation(fitted, monkeypatch, iters, accum, steps):
    import dynslam_cli.slam.system as system

    cfg, state = fitted
    monkeypatch.setattr(system, "POSE_ACCUM_STEPS", accum)
    cfg2 = tiny_config(**{"mapping.iters": iters, "mapping.every": 1})
    slam = _load(cfg2, state)
    pose_steps = []
    orig = torch.optim.Adam.step

    def spy(self, *a, **k):
        if any(p.dim() == 2 and p.shape[-1] == 6 for g in self.param_groups for p in g["params"]):
            pose_steps.append(1)
        return orig(self, *a, **k)

    monkeypatch.setattr(torch.optim.Adam, "step", spy)
    before = slam.poses[0].copy()
    res = slam.process(F(1, se3_exp_np([0.01, 0, 0, 0, 0, 0]), INTR))
    assert res.map is not None and res.map.ba and len(pose_steps) == steps
    assert np.allclose(slam.poses[0], before)  # the first keyframe stays fixed


def test_retrack_replaces_the_last_pose_and_keeps_the_bookkeeping(fitted):
    cfg, state = fitted
    slam = _load(cfg, state)
    with pytest.raises(Exception, match="retrack"):
        slam.retrack(F(0, np.eye(4), INTR))
    true = se3_exp_np([0.02, -0.01, 0.01, 0.0, 0.01, 0.0])
    f1 = F(1, true, INTR)
    bad = np.zeros((INTR.height, INTR.width), bool)  # nothing usable: tracking is skipped
    first = slam.track(f1, bad)
    assert first.diverged and "usable" in first.reason
    n, prev = slam.n_frames, slam._undo[0]
    res = slam.retrack(f1, None)
    assert slam.n_frames == n and len(slam.timestamps) == n and len(slam.kf_of) == n and len(slam.rel) == n
    assert slam._undo[0] is prev and not res.diverged
    assert np.linalg.norm(res.pose_c2w[:3, 3] - true[:3, 3]) < 0.5 * np.linalg.norm(true[:3, 3])
    slam.map(f1)  # map() still accepts the retracked frame (it raises otherwise)


def test_final_bundle_adjustment_refines_keyframes_but_not_the_first(fitted):
    # mapping.final_iters: SLAM.finish() runs bundle adjustment after the last frame
    _, state = fitted

    def load(**over):
        s = SLAM(tiny_config(**{"tracking.icp_init": False, "mapping.every": 100, "mapping.keyframe_every": 1,
                                **over}), INTR, torch.device("cpu"))
        s.load_state_dict(state)
        return s

    poses = trajectory(3, step=0.01)
    off, on = load(), load(**{"mapping.final_iters": 10})
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


@pytest.mark.parametrize("lr,backend", [(0.001, False), (0.0, False), (0.001, True)])
def test_bundle_adjustment_moves_poses_only_without_the_backend_and_with_lr_pose(fitted, monkeypatch, lr, backend):
    cfg, state = fitted
    slam = _load(tiny_config(**{"mapping.lr_pose": lr}), state)
    seen = []
    real_adam = torch.optim.Adam
    monkeypatch.setattr(torch.optim, "Adam", lambda params, lr, **kw: seen.append(lr) or real_adam(params, lr=lr, **kw))
    slam.track(F(1, se3_exp_np([0.01, 0.0, 0.0, 0.0, 0.0, 0.0]), INTR))
    slam.map(F(1, se3_exp_np([0.01, 0.0, 0.0, 0.0, 0.0, 0.0]), INTR))  # not due: nothing optimised
    if backend:
        slam.backend = object()  # poses from a backend: bundle adjustment trains the map only
    slam._optimize(slam._cur, 2, 64, first=False)
    assert (lr in seen) == (lr > 0 and not backend)  # the pose optimiser runs with lr_pose, or not at all

