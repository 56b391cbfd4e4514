"""The composed backend (dynslam_cli.backend.backend.Backend) on a rendered textured wall, and the
keyframe policy (dynslam_cli.backend.keyframes)."""

import cv2
import numpy as np
import pytest

from dynslam_cli.backend.backend import Backend
from dynslam_cli.backend.config import BackendConfig
from dynslam_cli.backend.keyframes import LandmarkKeyframes, need_keyframe

W, H, FOC = 320, 240, 280.0
INTR = (FOC, FOC, W / 2, H / 2, W, H)


def _wall_texture(seed=0, n=400):
    rng = np.random.default_rng(seed)
    blocks = rng.integers(0, 256, (n // 8, n // 8)).astype(np.uint8)
    tex = cv2.resize(blocks, (n, n), interpolation=cv2.INTER_NEAREST)
    return cv2.GaussianBlur(tex, (3, 3), 0.8)


TEX = _wall_texture()


def _camera(i: int) -> np.ndarray:
    """Frame i: moving right 2 cm and yawing 0.3 degrees per frame."""
    a = np.radians(0.3 * i)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [0.02 * i, 0.0, 0.0]
    return T


def _render(T):
    """RGB and depth of the wall z = 2.5 + 0.3 x and, in front of it, a panel z = 1.2 over
    -0.2 < x < 0.4 (world; texture over x, y in [-3, 3])."""
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    dc = np.stack([(uu - W / 2) / FOC, (vv - H / 2) / FOC, np.ones_like(uu)], -1)
    d = dc @ T[:3, :3].T
    o = T[:3, 3]
    t = (2.5 + 0.3 * o[0] - o[2]) / (d[..., 2] - 0.3 * d[..., 0])  # o + t d on the wall; t = camera depth
    t_panel = (1.2 - o[2]) / d[..., 2]
    x_panel = o[0] + t_panel * d[..., 0]
    t = np.where((x_panel > -0.2) & (x_panel < 0.4), t_panel, t)
    p = o + t[..., None] * d
    n = TEX.shape[0]
    g = cv2.remap(TEX, ((p[..., 0] + p[..., 2] + 3) / 6 * (n - 1)).astype(np.float32),
                  ((p[..., 1] + 3) / 6 * (n - 1)).astype(np.float32), cv2.INTER_LINEAR)
    return np.repeat(g[..., None], 3, 2), t.astype(np.float32)


FRAMES = [_render(_camera(i)) for i in range(10)]
CFG = BackendConfig(features=400, window=4)
CFG.KEYFRAME_MAX_GAP = 4  # a short sequence: the gap policy within it


def _run(be, frames, start=0, static=None):
    return [be.track(start + i, rgb, d, static) for i, (rgb, d) in enumerate(frames)]


def test_tracks_a_rendered_sequence_with_keyframes():
    be = Backend(INTR, CFG)
    outs = _run(be, FRAMES)
    assert outs[0].keyframe and outs[0].reason == "first"
    assert not any(o.lost for o in outs) and all(o.inliers >= 100 for o in outs[1:])
    for i, o in enumerate(outs):  # the first pose is the identity, as the truth's
        assert np.linalg.norm(o.pose_c2w[:3, 3] - _camera(i)[:3, 3]) < 0.01, i
    kfs = be.keyframe_poses()
    assert 0 in kfs and 2 <= len(kfs) <= 6  # the policy fired (gap 4 at most), not every frame
    for f, T in kfs.items():
        assert np.linalg.norm(T[:3, 3] - _camera(f)[:3, 3]) < 0.01
    assert be.trajectory().shape == (10, 4, 4)


def test_keyframe_policy():
    assert need_keyframe(0, 0, 0, 0, 0, 0.75, 30) == (True, "first")
    assert need_keyframe(200, 300, 3, 10, 5, 0.75, 30)[0]  # 200 < 0.75 * 300
    assert not need_keyframe(260, 300, 3, 10, 5, 0.75, 30)[0]
    assert need_keyframe(260, 300, 30, 10, 5, 0.75, 30)[0]  # max gap
    assert need_keyframe(80, 100, 3, 90, 5, 0.75, 30)[0]  # few tracked, many new close points
    assert not need_keyframe(10, 300, 3, 10, 5, 0.75, 30)[0]  # too few to be a keyframe at all
    assert not need_keyframe(150, 300, 3, 10, 1, 0.75, 30)[0]  # one keyframe: ORB-SLAM's 0.4


def test_lost_when_too_few_static_matches():
    be = Backend(INTR, CFG)
    _run(be, FRAMES[:3])
    v1 = be.last_pose @ np.linalg.inv(be.prev_pose)
    blank = np.zeros((H, W), bool)
    blank[:40, :40] = True  # almost everything masked: a few keypoints at most
    out = be.track(3, *FRAMES[3], blank)
    assert out.lost and out.reason.startswith("lost:") and not out.keyframe and out.inliers == 0
    cv = v1 @ be.prev_pose  # constant velocity (the motion model's velocity is filtered: close, not equal)
    assert np.linalg.norm(out.pose_c2w[:3, 3] - cv[:3, 3]) < 2e-3, np.linalg.norm(out.pose_c2w[:3, 3] - cv[:3, 3])
    assert not be.track(4, *FRAMES[4]).lost  # and it picks up again


def test_masked_pixels_never_create_landmarks():
    static = np.ones((H, W), bool)
    static[:, : W // 2] = False  # left half dynamic
    be = Backend(INTR, CFG)
    _run(be, FRAMES[:6], static=static)
    assert be.lm.n_alive > 50
    assert (be.lm.obs_uv[:, 0] >= W // 2 - 0.5).all()  # every observation on a static pixel
    for k, f in enumerate(be.kf_frame):
        created = be.lm.first_kf == k
        uv = (be.lm.pos[created] - _camera(f)[:3, 3]) @ _camera(f)[:3, :3]
        assert (FOC * uv[:, 0] / uv[:, 2] + W / 2 > W // 2 - 2).all()


def test_state_dict_round_trip_continues_identically():
    straight = Backend(INTR, CFG)
    ref = _run(straight, FRAMES)
    first = Backend(INTR, CFG)
    _run(first, FRAMES[:5])
    state = {k: np.array(v) for k, v in first.state_dict().items()}
    kf_state = {k: np.array(v) for k, v in first.keyframes.state_dict().items()}
    assert all(isinstance(v, np.ndarray) for v in state.values())
    resumed = Backend(INTR, CFG)
    resumed.keyframes.load_state_dict(kf_state)  # the keyframe store's part
    resumed.load_state_dict(state)
    rest = _run(resumed, FRAMES[5:], start=5)
    for a, b in zip(ref[5:], rest, strict=False):
        assert np.array_equal(a.pose_c2w, b.pose_c2w) and a.keyframe == b.keyframe and a.inliers == b.inliers
    assert np.array_equal(straight.trajectory(), resumed.trajectory())
    # the frames' matches came through the checkpoint: the same refined trajectory
    (ra, na), (rb, nb) = straight.refined_trajectory(), resumed.refined_trajectory()
    assert na == nb > 0 and np.array_equal(ra, rb)


def test_refined_trajectory_keeps_keyframes_and_moves_the_other_frames_little():
    be = Backend(INTR, CFG)
    _run(be, FRAMES)
    raw = be.trajectory()
    refined, n = be.refined_trajectory()
    kf_rows = set(int(f) for f in be.kf_frame)  # rows are frame indices here
    assert refined.shape == raw.shape and n == len(FRAMES) - len(kf_rows)
    for i in range(len(FRAMES)):
        if i in kf_rows:
            assert np.array_equal(refined[i], raw[i])
        else:  # solved again on the same matches: close to the truth, as the tracked pose was
            assert np.linalg.norm(refined[i][:3, 3] - _camera(i)[:3, 3]) < 0.01, i


@pytest.mark.parametrize("bad", ["features=0", "window=1"])
def test_config_rules(bad):
    from dynslam_cli.config.fields import rule_of
    import dataclasses

    key, value = bad.split("=")
    f = {x.name: x for x in dataclasses.fields(BackendConfig)}[key]
    assert rule_of(f).violation(int(value)) is not None


def test_deferred_keyframe_uses_the_final_mask_and_tags_instances():
    """With defer, the keyframe waits for commit(): no landmark on pixels the final mask drops, and
    each landmark carries the instance id under it, so keyframes.forget() leaves out an instance's landmarks
    while it is called dynamic and takes them back when it is called static again."""
    be = Backend(INTR, CFG)
    rgb, d = FRAMES[0]
    out = be.track(0, rgb, d, None, defer=True)
    assert out.keyframe and len(be.kf_frame) == 0  # due, not yet inserted
    ids = np.zeros((H, W), np.int32)
    ids[:, W // 2:] = 7  # the right half is instance 7
    static = np.ones((H, W), bool)
    static[:, : W // 4] = False  # the final mask drops the left quarter
    inserted, _, pose = be.commit(static, ids)
    assert inserted and len(be.kf_frame) == 1 and np.allclose(pose, np.eye(4))
    u = be.lm.obs_uv[:, 0]
    assert len(u) > 50 and (u >= W // 4 - 1).all()  # nothing made on the dropped quarter
    right = be.lm.origin == 7
    assert right.any() and (be.lm.origin[~right] == 0).all()
    assert be.commit(static, ids) == (False, 0.0, None)  # nothing pending any more
    everything = be.lm.seen_by([0])
    assert be.keyframes.forget(5, [7]) == 0  # frame 5 is no keyframe
    assert be.keyframes.forget(0, [7]) == int(right.sum())
    assert set(be.lm.seen_by([0])) == set(everything) - set(np.flatnonzero(right))
    outs = [be.track(i, *FRAMES[i], None) for i in range(1, 4)]  # the rest still tracks
    assert not any(o.lost for o in outs)
    assert be.keyframes.forget(0, []) == 0  # called static again: back in the local map
    assert set(np.flatnonzero(right)) <= set(be.lm.seen_by([0]))


def test_correct_last_moves_the_motion_model():
    be = Backend(INTR, CFG)
    _run(be, FRAMES[:3])
    T = _camera(2).copy()
    T[:3, 3] += [0.0, 0.05, 0.0]
    be.correct_last(T)
    assert np.allclose(be.trajectory()[-1], T) and np.allclose(be.last_pose, T)


def test_not_initialised_starts_where_the_caller_put_the_camera():
    """Frames with too few keypoints are lost; the caller's corrected poses place the first keyframe."""
    be = Backend(INTR, CFG)
    blank = (np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.float32))
    out = be.track(0, *blank)
    assert out.lost and "not initialised" in out.reason and len(be.kf_frame) == 0
    be.correct_last(_camera(0))
    be.track(1, *blank)
    be.correct_last(_camera(1))
    out = be.track(2, *FRAMES[2])
    assert not out.lost and out.reason == "first"
    assert np.linalg.norm(out.pose_c2w[:3, 3] - _camera(2)[:3, 3]) < 1e-3  # constant velocity from frames 0, 1


def test_retrack_on_the_keypoints_still_static():
    be = Backend(INTR, CFG)
    assert be.retrack(np.ones((H, W), bool)) is None  # nothing tracked yet
    _run(be, FRAMES[:3])
    assert be.retrack(np.ones((H, W), bool)) is None  # no keypoint dropped: the pose stands
    static = np.ones((H, W), bool)
    static[:, W // 3: 2 * W // 3] = False  # the check found a mover in the middle third
    pose = be.retrack(static)
    assert pose is not None and np.linalg.norm(pose[:3, 3] - _camera(2)[:3, 3]) < 0.01
    assert np.allclose(be.trajectory()[-1], pose) and np.allclose(be.last_pose, pose)
    assert be.retrack(np.zeros((H, W), bool)) is None  # nothing static left: the pose stands
    assert np.allclose(be.trajectory()[-1], pose)


def test_tracks_the_same_with_the_landmarks_compacted_every_frame(monkeypatch):
    from dynslam_cli.backend import landmarks

    be = Backend(INTR, CFG)
    monkeypatch.setattr(landmarks, "COMPACT_MIN_ROWS", 10 ** 9)  # never
    ref = [o.pose_c2w for o in _run(be, FRAMES)]
    never = len(be.lm)
    monkeypatch.setattr(landmarks, "COMPACT_MIN_ROWS", 0)
    monkeypatch.setattr(landmarks, "COMPACT_DEAD_FRACTION", 0.0)  # whenever a landmark died
    be2 = Backend(INTR, CFG)
    outs = _run(be2, FRAMES)
    assert len(be2.lm) < never and be2.lm.alive.sum() == be.lm.alive.sum()  # culled rows went
    for o, T in zip(outs, ref, strict=False):
        assert np.array_equal(o.pose_c2w, T)
    assert np.array_equal(be2.trajectory(), be.trajectory())
    for k in ("pos", "des", "origin", "first_kf", "visible", "found"):
        assert np.array_equal(getattr(be2.lm, k)[be2.lm.alive], getattr(be.lm, k)[be.lm.alive]), k


def test_frame_rows_append_and_survive_a_state_round_trip():
    be = Backend(INTR, CFG)
    rng = np.random.default_rng(0)
    refs, rels = rng.integers(-1, 5, 150), rng.normal(size=(150, 4, 4))
    for r, T in zip(refs[:100], rels[:100], strict=False):  # past the first capacity (64)
        be._append_frame(int(r), T)
    assert np.array_equal(be.frame_ref, refs[:100]) and np.array_equal(be.frame_rel, rels[:100])
    be.frame_rel[-1] = np.eye(4)  # the last row can be replaced in place (retrack, commit)
    other = Backend(INTR, CFG)
    other.load_state_dict(be.state_dict())
    for r, T in zip(refs[100:], rels[100:], strict=False):
        other._append_frame(int(r), T)
    assert np.array_equal(other.frame_ref, refs) and np.array_equal(other.frame_rel[100:], rels[100:])
    assert np.array_equal(other.frame_rel[99], np.eye(4)) and np.array_equal(other.frame_rel[:99], rels[:99])


def test_state_without_a_motion_model_loads():
    """A checkpoint written before the motion model existed resumes; its filter starts afresh."""
    be = Backend(INTR, CFG)
    _run(be, FRAMES[:4])
    old = {k: v for k, v in be.state_dict().items() if not k.startswith("motion.")}
    be2 = Backend(INTR, CFG)
    be2.keyframes.load_state_dict(be.keyframes.state_dict())
    be2.load_state_dict(old)
    assert not be2.motion.v.any() and np.array_equal(be2.last_pose, be.last_pose)
    assert not be2.track(4, *FRAMES[4]).lost



def test_reprojection_evidence_of_the_last_tracked_frame():
    be = Backend(INTR, CFG)
    assert be.reprojection_evidence() is None
    be.track(0, *FRAMES[0])
    assert be.reprojection_evidence() is None  # the first frame is not tracked against a map
    be.track(1, *FRAMES[1])
    uv, ok = be.reprojection_evidence()
    assert uv.shape == (len(ok), 2) and len(ok) >= 100 and ok.mean() > 0.9  # a still scene reprojects


def test_a_place_seen_again_is_tracked_against_its_old_landmarks(monkeypatch):
    """Out 0.8 m along the wall and back, with a local map of 4 covisible keyframes: the first
    keyframe's landmarks have left it by the turn; back at the start, the frames match them again
    (LandmarkKeyframes.in_view) instead of only the landmarks made on the way back, and the drift
    of the way out and back is gone."""
    def cam(i):
        T = np.eye(4)
        T[0, 3] = 0.4 * (1 - np.cos(np.pi * i / 40))  # out and back, turning smoothly
        return T

    frames = [_render(cam(i)) for i in range(81)]
    cfg = BackendConfig(features=400, window=2)
    cfg.KEYFRAME_MAX_GAP = 4

    def run():
        be = Backend(INTR, cfg)
        outs = _run(be, frames)
        assert not any(o.lost for o in outs)
        lm = be.lm
        late = np.isin(lm.obs_kf, np.flatnonzero(be.kf_frame > 70))  # keyframes back near the start
        old = int((lm.first_kf[lm.obs_lm[late]] == 0).sum())  # their observations of the first keyframe's landmarks
        err = max(np.linalg.norm(o.pose_c2w[:3, 3] - cam(i)[:3, 3]) for i, o in enumerate(outs) if i > 70)
        return old, err

    old, err = run()
    assert old >= 100 and err < 0.02
    monkeypatch.setattr(LandmarkKeyframes, "in_view", lambda self, *a, **k: [])
    old, err = run()
    assert old < 50 and err > 0.04  # covisibility alone does not reach them: the way back drifts


def test_reprojection_evidence_leaves_out_landmarks_of_a_place_seen_again(monkeypatch):
    """Back near the start of an out-and-back path, tracking matches the first keyframes'
    landmarks again (LandmarkKeyframes.in_view); the drift gathered on the way is theirs all
    together, so they are no evidence that anything moved: the evidence keeps only the matches of
    landmarks the covisible window observed.  Frames that match no such keyframe keep them all."""
    def cam(i):
        T = np.eye(4)
        T[0, 3] = 0.4 * (1 - np.cos(np.pi * i / 40))
        return T

    cfg = BackendConfig(features=400, window=2)
    cfg.KEYFRAME_MAX_GAP = 4
    calls = []
    in_view = LandmarkKeyframes.in_view
    monkeypatch.setattr(LandmarkKeyframes, "in_view",
                        lambda self, *a, **k: calls.append(in_view(self, *a, **k)) or calls[-1])
    be = Backend(INTR, cfg)
    seen_again, plain = [], []
    for i in range(81):
        out = be.track(i, *_render(cam(i)))
        assert not out.lost
        if i == 0:
            continue
        in_window = be._evidence[3]  # per match: a landmark of the covisible window
        uv, ok = be.reprojection_evidence()
        assert len(ok) <= int(in_window.sum())
        (seen_again if calls[-1] else plain).append((int(in_window.sum()), len(in_window), len(ok)))
    assert plain and all(n == m for n, m, _ in plain)  # on the way out every match counts
    assert seen_again and any(n < m for n, m, _ in seen_again)  # back at the start the old landmarks do not
    assert all(k >= 20 for _, _, k in seen_again)  # the window's own matches still do
