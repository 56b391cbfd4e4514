import numpy as np
import pytest
import torch

from dynslam_cli.geometry.lie import se3_exp_np
from dynslam_cli.slam import frontend
from dynslam_cli.slam.frontend import Frontend, first_pose, off_velocity
from dynslam_cli.slam.state import SlamState
from dynslam_cli.slam.toyscene import TinyIntrinsics, ToyFrame, first_frame_state, load_slam, tiny_config

INTR = TinyIntrinsics(48, 36, f=20.0)


@pytest.fixture(scope="module")
def fitted():
    cfg = tiny_config()
    return cfg, first_frame_state(cfg, INTR)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    torch.set_num_threads(1)  # 2 shared cores: no OpenMP spin-waiting (conftest puts the count back)


def test_tracking_recovers_a_small_perturbation(fitted):
    cfg, state = fitted
    slam = load_slam(cfg, INTR, state)
    true = se3_exp_np([0.03, -0.02, 0.02, 0.01, -0.015, 0.01])
    res = slam.track(ToyFrame(1, true, INTR))
    assert not res.diverged and res.iters == cfg.tracking.iters
    before = np.linalg.norm(true[:3, 3])
    after = np.linalg.norm(res.pose_c2w[:3, 3] - true[:3, 3])
    assert after < 0.5 * before, (before, after)


def test_divergence_falls_back_to_the_constant_velocity_pose(fitted, monkeypatch):
    cfg, state = fitted
    monkeypatch.setattr(frontend, "MAX_JUMP", 1e-9)
    slam = load_slam(cfg, INTR, state)
    res = slam.track(ToyFrame(1, se3_exp_np([0.03, 0, 0, 0, 0, 0]), INTR))
    assert res.diverged and "jump" in res.reason
    assert np.allclose(res.pose_c2w, np.eye(4)) and slam.events[-1]["frame"] == 1
    slam2 = load_slam(cfg, INTR, state)
    slam2.model.query = lambda pts, color=True, grid_extra=None: (
        torch.full((len(pts),), float("nan")), torch.zeros(len(pts), 3), None)
    res2 = slam2.track(ToyFrame(1, np.eye(4), INTR))
    assert res2.diverged and "non-finite" in res2.reason and np.all(np.isfinite(res2.pose_c2w))
    monkeypatch.undo()


def test_retrack_replaces_the_last_pose_and_aligns_to_the_previous_frame_again(fitted, monkeypatch):
    cfg, state = fitted
    slam = load_slam(cfg, INTR, state)
    with pytest.raises(Exception, match="retrack"):
        slam.retrack(ToyFrame(0, np.eye(4), INTR))
    refs = []
    icp = frontend.icp_depth
    monkeypatch.setattr(frontend, "icp_depth", lambda ref, *a, **k: refs.append(ref) or icp(ref, *a, **k))
    true = se3_exp_np([0.02, -0.01, 0.01, 0.0, 0.01, 0.0])
    f1 = ToyFrame(1, true, INTR)
    bad = np.zeros((INTR.height, INTR.width), bool)  # nothing usable: tracking is skipped
    frame0_ref = slam.frontend.prev_depth
    first = slam.track(f1, bad)
    assert first.diverged and "usable" in first.reason
    assert not slam.frontend.prev_depth.any()  # frame 1's ICP reference: no static pixel
    n = slam.n_frames
    res = slam.retrack(f1, None)
    assert slam.n_frames == n and len(slam.timestamps) == n and len(slam.kf_of) == n and len(slam.rel) == n
    assert len(refs) == 2 and refs[0] is frame0_ref and refs[1] is frame0_ref  # not frame 1's empty one
    assert slam.frontend.prev_depth.any() and not res.diverged
    assert np.linalg.norm(res.pose_c2w[:3, 3] - true[:3, 3]) < 0.5 * np.linalg.norm(true[:3, 3])
    slam.map(f1)  # map() still accepts the retracked frame (it raises otherwise)


def test_off_velocity_and_a_rejected_guess_is_an_event():
    rel = se3_exp_np([0.01, 0, 0, 0, 0, 0])
    far = se3_exp_np([0.51, 0, 0, 0, 0, 0])
    assert off_velocity(far, rel) == pytest.approx(0.5)
    fe = Frontend(SlamState(tiny_config(), INTR, torch.device("cpu")))
    assert fe.plausible(rel, rel, "ICP", 3) and fe.s.events == []
    assert not fe.plausible(far, rel, "ICP", 3)
    assert fe.s.events == [{"frame": 3, "kind": "guess_rejected",
                            "detail": f"ICP step 0.500 m from constant velocity > {frontend.MAX_JUMP} m"}]


def test_constant_velocity_prediction_and_first_pose():
    state = SlamState(tiny_config(), INTR, torch.device("cpu"))
    step = se3_exp_np([0.01, -0.02, 0.0, 0.0, 0.02, 0.0])
    state.poses = [np.eye(4), step]
    assert np.allclose(Frontend(state).predict_pose(), step @ step, atol=1e-9)
    pose = se3_exp_np([0.1, 0, 0, 0, 0, 0])
    assert np.array_equal(first_pose(ToyFrame(0, pose, INTR)), pose)
    assert np.array_equal(first_pose(ToyFrame(0, pose, INTR, with_gt=False)), np.eye(4))


def test_set_mask_follows_the_final_static_mask():
    state = SlamState(tiny_config(), INTR, torch.device("cpu"))
    fe = Frontend(state)
    cur = state.prepare(ToyFrame(0, np.eye(4), INTR), None)
    n = len(cur.valid)
    mask = np.ones((INTR.height, INTR.width), bool)
    mask[:, :INTR.width // 2] = False
    fe.set_mask(cur, mask)
    assert 0 < len(cur.valid) < n and np.all(mask.reshape(-1)[cur.valid])
    assert not fe.prev_depth[:, :INTR.width // 2].any() and fe.prev_depth[:, INTR.width // 2 + 3:-3].all()
