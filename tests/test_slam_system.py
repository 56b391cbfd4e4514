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


def test_divergence_falls_back_to_the_constant_velocity_pose(fitted):
    cfg, state = fitted
    cfg2 = tiny_config()
    cfg2.tracking.max_jump = 1e-9
    slam = _load(cfg2, state)
    res = slam.track(F(1, se3_exp_np([0.03, 0, 0, 0, 0, 0]), INTR))
    assert res.diverged and "jump" in res.reason
    assert np.allclose(res.pose_c2w, np.eye(4)) and slam.events[-1]["frame"] == 1
    slam2 = _load(cfg, state)
    slam2.model.query = lambda pts, color=True, grid_extra=None: (
        torch.full((len(pts),), float("nan")), torch.zeros(len(pts), 3), None)
    res2 = slam2.track(F(1, np.eye(4), INTR))
    assert res2.diverged and "non-finite" in res2.reason and np.all(np.isfinite(res2.pose_c2w))


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
    cfg = tiny_config(**{"tracking.edge_margin": 2, "mapping.edge_margin": 2, "mapping.first_iters": 2})
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
    cfg, state = fitted
    cfg2 = tiny_config(**{"mapping.iters": iters, "mapping.pose_accum_steps": accum, "mapping.every": 1})
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


@pytest.mark.parametrize("feature_init", [True, False])
def test_feature_init_poses_a_textured_frame_and_keeps_its_reference(feature_init):
    from test_geometry_features import F as FOCAL
    from test_geometry_features import H as HT
    from test_geometry_features import W as WT
    from test_geometry_features import _render, _texture

    intr = TinyIntrinsics(WT, HT, f=FOCAL)
    cfg = tiny_config(**{"tracking.iters": 0, "tracking.icp_init": False, "tracking.feature_init": feature_init,
                         "tracking.feature_count": 1000, "mapping.first_iters": 2, "map.bounds": "null"})
    tex = _texture()
    poses = [np.eye(4), se3_exp_np([0.03, -0.01, 0.04, 0.01, -0.02, 0.0]),
             se3_exp_np([0.05, -0.02, 0.07, 0.015, -0.03, 0.005])]

    class TF:
        def __init__(self, i):
            self.index, self.timestamp, self.pose_c2w = i, float(i), poses[0] if i == 0 else None
            self.rgb, self.depth = _render(poses[i], tex)

    slam = SLAM(cfg, intr, torch.device("cpu"))
    slam.process(TF(0))
    r1 = slam.process(TF(1))
    if not feature_init:  # constant velocity from one pose: the identity
        assert slam.last_pnp is None and np.allclose(r1.pose_c2w, np.eye(4))
        return
    assert slam.last_pnp.ok and slam.last_pnp.inliers > 100
    assert np.linalg.norm(r1.pose_c2w[:3, 3] - poses[1][:3, 3]) < 0.015
    assert [f for f, _ in slam._feat_refs] == [0]  # many inliers: frame 0 stays the only reference
    assert slam.last_pnp.ref_inliers == (slam.last_pnp.inliers,)
    state = slam.state_dict()
    r2 = slam.process(TF(2))
    assert np.linalg.norm(r2.pose_c2w[:3, 3] - poses[2][:3, 3]) < 0.015
    back = SLAM(cfg, intr, torch.device("cpu"))
    back.load_state_dict(state)
    assert [f for f, _ in back._feat_refs] == [0]
    assert np.array_equal(back._feat_refs[0][1].des, state["feat_refs"][0]["des"])
    assert np.allclose(back.process(TF(2)).pose_c2w, r2.pose_c2w)
    # a feature step farther than tracking.max_jump from constant velocity is not used, and logged
    cfg.tracking.max_jump = 0.01
    tight = SLAM(cfg, intr, torch.device("cpu"))
    tight.process(TF(0))
    assert np.allclose(tight.process(TF(1)).pose_c2w, np.eye(4))
    assert [e["kind"] for e in tight.events] == ["guess_rejected"] and tight.events[0]["frame"] == 1
    # tracking.feature_min_inlier_ratio: a guess from far fewer inliers than the previous frame's is not used
    from dynslam_cli.geometry.features import PnPResult

    class Odometry:  # PnP 'finds' the true pose, from 400 inliers on frame 1 and from 100 on frame 2
        def __init__(self, real):
            self.calls, self.detect = 0, real.detect

        def estimate_multi(self, refs, feats):
            self.calls += 1
            return PnPResult(poses[self.calls], 500, 400 if self.calls == 1 else 100, True, (1,))

    cfg.tracking.max_jump = 0.3
    for ratio, kinds in ((0.0, []), (0.5, ["guess_rejected"])):
        cfg.tracking.feature_min_inlier_ratio = ratio
        s = SLAM(cfg, intr, torch.device("cpu"))
        s.process(TF(0))
        s._odometry = Odometry(s._feature_odometry())
        assert np.allclose(s.process(TF(1)).pose_c2w, poses[1])
        r = s.process(TF(2))
        assert np.allclose(r.pose_c2w, poses[2]) == (ratio == 0.0)  # else constant velocity from frame 1
        assert [e["kind"] for e in s.events] == kinds
        assert s.state_dict()["pnp_inliers"] == {1: 400, 2: 100}


def test_iters_dynamic_replaces_the_tracking_iterations_in_dynamic_mode(fitted):
    cfg, state = fitted
    true = se3_exp_np([0.01, 0.0, 0.0, 0.0, 0.0, 0.0])
    for mode, it_dyn, want in [("static", 0, 10), ("dynamic", 0, 0), ("dynamic", 3, 3), ("dynamic", -1, 10)]:
        c = tiny_config(**{"run.mode": mode, "tracking.iters_dynamic": it_dyn})
        slam = _load(c, state)
        assert slam.tracking_iters == want
        assert slam.track(F(1, true, INTR)).iters == want


@pytest.mark.parametrize("mode,refs_dyn,lr_dyn,refs,lr", [("static", 8, 0.0, 1, 0.001), ("dynamic", 8, 0.0, 8, 0.0),
                                                          ("dynamic", -1, -1.0, 1, 0.001)])
def test_feature_refs_and_pose_learning_rate_have_dynamic_mode_values(fitted, monkeypatch, mode, refs_dyn, lr_dyn,
                                                                      refs, lr):
    cfg, state = fitted
    c = tiny_config(**{"run.mode": mode, "tracking.feature_refs_dynamic": refs_dyn,
                       "mapping.lr_pose_dynamic": lr_dyn, "mapping.lr_pose": 0.001})
    slam = _load(c, state)
    assert (slam.feature_refs, slam.lr_pose) == (refs, lr)
    seen = []
    real_adam = torch.optim.Adam
    monkeypatch.setattr(torch.optim, "Adam", lambda params, lr, **kw: seen.append(lr) or real_adam(params, lr=lr, **kw))
    slam.track(F(1, se3_exp_np([0.01, 0.0, 0.0, 0.0, 0.0, 0.0]), INTR))
    slam.map(F(1, se3_exp_np([0.01, 0.0, 0.0, 0.0, 0.0, 0.0]), INTR))  # not due: nothing optimised
    slam._optimize(slam._cur, 2, 64, first=False)
    assert (lr in seen) == (lr > 0)  # the pose optimiser runs with lr_pose, or not at all


def test_map_residual_is_lowest_at_the_true_pose_and_verification_rejects_a_wrong_feature_step():
    from dynslam_cli.geometry.features import PnPResult

    torch.manual_seed(0)
    cfg = tiny_config(**{"tracking.iters": 0, "tracking.icp_init": False, "tracking.feature_init": True})
    first = SLAM(cfg, INTR, torch.device("cpu"))
    first.process(F(0, np.eye(4), INTR))
    state = first.state_dict()
    true = se3_exp_np([0.01, 0.0, 0.0, 0.0, 0.0, 0.0])
    probe = _load(cfg, state)
    cur = probe._prepare(F(1, true, INTR), None)
    at_true = probe.map_residual(cur, true)
    assert at_true < 0.02 and at_true == probe.map_residual(cur, true)  # same rays every call
    # a feature step 16 cm from constant velocity, diagonal: a step along one axis of the box moves few walls' depth
    far = se3_exp_np([0.1, 0.08, 0.1, 0.0, 0.0, 0.0])
    assert probe.map_residual(cur, far) > 5 * at_true

    class Odometry:
        def __init__(self, real, pose):
            self.detect, self.pose = real.detect, pose

        def estimate_multi(self, refs, feats):
            return PnPResult(self.pose, 500, 400, True, (400,))

    for verify, frame_pose, kept in ((0.0, true, True), (0.1, true, False), (0.1, far, True)):
        cfg.tracking.feature_verify = verify
        s = _load(cfg, state)
        s._odometry = Odometry(s._feature_odometry(), far)
        r = s.track(F(1, frame_pose, INTR))
        # kept: PnP's pose; rejected: constant velocity from one pose, the identity
        assert np.allclose(r.pose_c2w, far if kept else np.eye(4))
        assert [e["kind"] for e in s.events] == ([] if kept else ["guess_rejected"])
    # tracking.feature_verify_min_static: too few static pixels to judge a far step, it is refused
    for min_static, kept in ((0.01, True), (1.01, False)):
        cfg.tracking.feature_verify, cfg.tracking.feature_verify_min_static = 0.1, min_static
        s = _load(cfg, state)
        s._odometry = Odometry(s._feature_odometry(), far)
        r = s.track(F(1, far, INTR))
        assert np.allclose(r.pose_c2w, far if kept else np.eye(4))
        assert [e["detail"].split(",")[0].split()[-1] for e in s.events] == ([] if kept else ["static"])
