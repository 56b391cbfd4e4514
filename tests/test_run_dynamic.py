"""Dynamic mode end to end (motion module wired into the SLAM loop) and its pieces."""

import json
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.run.dynamic import DynamicLoop
from dynslam_cli.slam.keyframes import Keyframe, subsample_depth
from tiny_runs import check_from_frame_2, render_walker, tiny_sets

TINY = tiny_sets()


@pytest.fixture(autouse=True)
def early_check(monkeypatch):
    check_from_frame_2(monkeypatch)


@pytest.fixture(scope="module")
def walker(tmp_path_factory):
    return render_walker(tmp_path_factory, 96, 72, 10)


def _traj(path):
    rows = [ln.split() for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    return np.array([[float(v) for v in r] for r in rows])


def test_dynamic_run_writes_masks_updates_and_timing(walker, tmp_path, monkeypatch):
    monkeypatch.setattr("dynslam_cli.run.dynamic.RETRACK_FRACTION", 0.0001)
    out = tmp_path / "dyn"
    res = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "dynamic", "--out", str(out),
                                   "--save-masks", "-q"] + TINY)
    assert res.exit_code == 0, res.output
    meta = json.loads((out / "run.json").read_text())
    assert meta["status"] == "completed" and meta["mode"] == "dynamic"
    stamps = [ln.split()[0] for ln in (walker / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    masks = sorted(p.stem for p in (out / "masks").glob("*.png"))
    assert masks == sorted(stamps)
    renders = sorted(p.name for p in (out / "renders").glob("*_depth.png"))
    assert renders and all(r[: -len("_depth.png")] in stamps for r in renders)
    timing = json.loads((out / "timing.json").read_text())
    for k in ("segment", "encode", "track", "render", "check", "update", "map", "frame"):
        assert k in timing["median_ms"], k
    lines = (out / "classifier_updates.jsonl").read_text().splitlines()
    assert timing["classifier_updates"] == len(lines)
    for ln in lines:
        rec = json.loads(ln)
        assert {"frame", "labels", "loss_before", "loss_after", "replay_size", "keyframe_rays_masked"} <= set(rec)
        assert 1 <= rec["frame"] < 10
    recs = [json.loads(ln) for ln in lines]
    assert timing["retracked_frames"] == sum(r["retracked"] for r in recs)
    newly_dynamic = any(lab and not pre for r in recs for lab, pre in zip(r["labels"], r["predicted_before"], strict=True))
    assert timing["retracked_frames"] >= 1 or not newly_dynamic
    assert isinstance(timing["keyframe_rays_gone"], int) and timing["keyframe_rays_gone"] >= 0
    assert _traj(out / "traj_est.txt").shape == (10, 8)


def test_dynamic_run_with_carving_counts_the_rays_it_forgot(walker, tmp_path):
    from dynslam_cli.config import load_config

    assert load_config().run.carve_margin == 0  # off by default
    out = tmp_path / "carve"
    res = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "dynamic", "--out", str(out), "-q",
                                   "--set", "run.carve_margin=0.05"] + TINY)
    assert res.exit_code == 0, res.output
    timing = json.loads((out / "timing.json").read_text())
    assert timing["keyframe_rays_gone"] >= 0 and _traj(out / "traj_est.txt").shape == (10, 8)


def test_dynamic_resume_gives_the_same_result(walker, tmp_path):
    full, part = tmp_path / "full", tmp_path / "part"
    r1 = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "dynamic", "--out", str(full), "-q"] + TINY)
    assert r1.exit_code == 0, r1.output
    r2 = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "dynamic", "--out", str(part), "-q",
                                  "--stop-after", "5"] + TINY)
    assert r2.exit_code == 0, r2.output
    assert json.loads((part / "run.json").read_text())["status"] == "interrupted"
    r3 = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "dynamic", "--out", str(part), "-q",
                                  "--resume", "--stop-after", "5"] + TINY)
    assert r3.exit_code == 0, r3.output
    # the resumed call has its own --stop-after budget: 5 more frames finish the 10-frame clip
    assert json.loads((part / "run.json").read_text())["status"] == "completed"
    np.testing.assert_allclose(_traj(part / "traj_est.txt"), _traj(full / "traj_est.txt"), atol=1e-6)
    assert (part / "classifier_updates.jsonl").read_text() == (full / "classifier_updates.jsonl").read_text()


def _bare_loop(keyframes, intr):
    loop = DynamicLoop.__new__(DynamicLoop)
    loop.slam = SimpleNamespace(keyframes=keyframes, intr=intr, forget_landmarks=lambda fid, ids: 0)
    loop.mm = SimpleNamespace(m=SimpleNamespace(depth_threshold=0.3))
    return loop


def test_checkable_depth_drops_edges_and_unseen_space():
    intr = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    depth = np.full((48, 64), 2.0, np.float32)
    depth[20:30, 20:30] = 1.0  # a box in front of a wall
    kf = SimpleNamespace(pose_c2w=np.eye(4), depth_small=None)
    out, fwd = _bare_loop([kf], intr).checkable_depth(depth, np.eye(4), step=1)
    assert out[25, 25] == 1.0 and out[5, 5] == 2.0  # interiors kept
    assert out[20, 25] == 0 and out[19, 25] == 0 and out[25, 30] == 0  # both sides of the step dropped
    assert fwd.all()  # without a stored depth map the whole frustum counts as observed
    # the camera moved 1 m to the right: what it sees on its right was never in a keyframe's view
    moved = np.eye(4)
    moved[0, 3] = 1.0
    out2, _ = _bare_loop([kf], intr).checkable_depth(depth, moved, step=1)
    assert out2[5, 5] > 0 and np.all(out2[:, -5:] == 0)


def test_checkable_depth_knows_what_keyframes_saw_behind_occluders():
    intr = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    seen = np.full((48, 64), 2.0, np.float32)
    seen[20:32, 20:32] = 1.0  # the keyframe saw a box in front of the wall
    kf = SimpleNamespace(pose_c2w=np.eye(4), depth_small=subsample_depth(seen))
    now = np.full((48, 64), 2.0, np.float32)  # the box has gone ...
    now[4:12, 40:52] = 1.5  # ... and something new stands in front of the wall
    out, fwd = _bare_loop([kf], intr).checkable_depth(now, np.eye(4), step=1)
    assert not fwd[26, 26] and out[26, 26] == 2.0  # the wall behind the old box: never observed
    assert fwd[8, 46] and fwd[40, 5]  # free space / the wall the keyframe saw


def test_refresh_keyframes_masks_rays_of_dynamic_instances():
    kfs = [SimpleNamespace(frame_id=0, instance_ids=np.array([0, 1, 2, 2, -1]), usable=np.ones(5, bool), near_ids=None),
           SimpleNamespace(frame_id=5, instance_ids=np.array([1, 1, 0]), usable=np.zeros(3, bool), near_ids=None),
           # ray 0 lies within the mask dilation of instance 2, ray 1 next to instance 1 only
           SimpleNamespace(frame_id=10, instance_ids=np.array([1, 1]), usable=np.ones(2, bool),
                           near_ids=np.array([[2, 1], [1, 0]]))]
    loop = _bare_loop(kfs, None)
    dyn = {0: np.array([2]), 5: np.array([], np.int32), 10: np.array([2])}
    loop.mm = SimpleNamespace(keyframes=dyn, keyframe_dynamic_ids=lambda k: dyn[k])
    assert loop._refresh_keyframes() == 3
    assert kfs[0].usable.tolist() == [True, True, False, False, True]
    assert kfs[1].usable.tolist() == [True, True, True]  # reclassified static: remembered again
    assert kfs[2].usable.tolist() == [False, True]


def test_near_ids_and_the_dilated_static_mask():
    from dynslam_cli.motion.module import MotionModule

    ids = np.zeros((20, 40), np.int32)
    ids[5:15, 10:20] = 1
    ids[5:15, 20:30] = 2
    loop = _bare_loop([], None)
    loop.mm = SimpleNamespace(m=SimpleNamespace(mask_dilation=0.05))  # 2 px at width 40
    near = loop.near_ids(ids, np.array([[8, 10], [12, 10], [18, 10], [35, 10]]))
    assert near.tolist() == [[1, 0], [1, 1], [2, 1], [0, 0]]  # (max, min) id within 2 px
    mm = MotionModule.__new__(MotionModule)
    mm.m = SimpleNamespace(mask_dilation=0.05)
    static = mm._static_mask(ids, np.array([False, True]))
    assert not static[3:17, 18:32].any() and static[10, 17] and static[10, 32] and static[2, 25]


def test_closest_rendered_forgives_blurred_edges_not_movers():
    ren = np.full((20, 20), 3.0, np.float32)
    ren[5:15, 5:10] = 1.0  # the map's object, one pixel narrower than the observation
    obs = np.full((20, 20), 3.0, np.float32)
    obs[5:15, 5:11] = 1.0
    obs[2:6, 14:18] = 0.8  # a mover in front of the wall
    out = DynamicLoop.closest_rendered(ren, obs, radius=1)
    assert out[8, 10] == 1.0  # edge pixel: a neighbour agrees
    assert out[3, 16] == 3.0  # mover interior: nothing near agrees, still 2.2 m inconsistent
    np.testing.assert_array_equal(DynamicLoop.closest_rendered(ren, obs, radius=0), ren)


def test_stationary_instances_know_what_stayed_put():
    from dynslam_cli.slam.keyframes import stationary_instances

    intr = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    wall = np.full((48, 64), 3.0, np.float32)
    ids = np.zeros((48, 64), np.int32)
    ids[10:30, 10:25] = 1  # a box that has stood here all along
    ids[10:30, 40:55] = 2  # a box that just arrived
    now = wall.copy()
    now[10:30, 10:25] = 1.5
    now[10:30, 40:55] = 1.5
    before = wall.copy()
    before[10:30, 10:25] = 1.5  # the keyframes saw box 1 but only the wall where box 2 now is
    kfs = [SimpleNamespace(pose_c2w=np.eye(4), depth_raw_small=subsample_depth(before)) for _ in range(2)]
    assert stationary_instances(now, ids, np.eye(4), intr, kfs).tolist() == [True, False]
    assert not stationary_instances(now, ids, np.eye(4), intr, kfs[:1]).any()  # one keyframe is not enough
    gone = [SimpleNamespace(pose_c2w=np.eye(4), depth_raw_small=subsample_depth(wall)), kfs[0]]
    assert stationary_instances(now, ids, np.eye(4), intr, gone).tolist() == [False, False]
    # a keyframe that did not look there (no valid depth) neither confirms nor refutes ...
    blind = SimpleNamespace(pose_c2w=np.eye(4), depth_raw_small=subsample_depth(np.zeros_like(wall)))
    assert stationary_instances(now, ids, np.eye(4), intr, [blind] + kfs).tolist() == [True, False]
    # ... nor counts among the two that must have looked
    assert not stationary_instances(now, ids, np.eye(4), intr, [blind, kfs[0]]).any()
    turned = np.array([[0.0, 0, 1, 0], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]])  # looking along +x
    aside = SimpleNamespace(pose_c2w=turned, depth_raw_small=subsample_depth(wall))
    assert stationary_instances(now, ids, np.eye(4), intr, kfs + [aside]).tolist() == [True, False]
    # a keyframe that saw something in front of box 1 (a passer-by) did not look at it either
    passer = before.copy()
    passer[5:35, 5:30] = 0.8
    hidden = SimpleNamespace(pose_c2w=np.eye(4), depth_raw_small=subsample_depth(passer))
    assert stationary_instances(now, ids, np.eye(4), intr, kfs + [hidden]).tolist() == [True, False]
    assert not stationary_instances(now, ids, np.eye(4), intr, [hidden, kfs[0]]).any()


def test_stationary_window_and_tolerance_with_and_without_the_centre_feature():
    intr = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    depth = np.full((48, 64), 1.5, np.float32)
    ids = np.ones((48, 64), np.int32)
    kfs = [SimpleNamespace(frame_id=i, pose_c2w=np.eye(4), depth_raw_small=subsample_depth(depth)) for i in (2, 4)]

    def loop(centre, tol=0.0, frames=10):
        return SimpleNamespace(still_frames=frames, still_tolerance=tol,
                               mm=SimpleNamespace(m=SimpleNamespace(centre_feature=centre, depth_threshold=0.3)),
                               slam=SimpleNamespace(n_frames=6, keyframes=kfs, intr=intr))

    # the stayed-put test applies with and without the centre feature; run.still_frames 0 turns it off
    assert DynamicLoop.stationary(loop(False), depth, ids, np.eye(4)).tolist() == [True]
    assert DynamicLoop.stationary(loop(True), depth, ids, np.eye(4)).tolist() == [True]
    assert DynamicLoop.stationary(loop(False, frames=0), depth, ids, np.eye(4)) is None
    # run.still_tolerance: 10 cm closer than the keyframes saw is 'stayed put' within t_d (0 = 0.3 m)
    # but not within 5 cm, with or without the centre feature
    closer = depth - 0.1
    assert DynamicLoop.stationary(loop(False), closer, ids, np.eye(4)).tolist() == [True]
    assert DynamicLoop.stationary(loop(False, 0.05), closer, ids, np.eye(4)).tolist() == [False]
    assert DynamicLoop.stationary(loop(True, 0.05), closer, ids, np.eye(4)).tolist() == [False]
    assert DynamicLoop.stationary(loop(False, 0.15), closer, ids, np.eye(4)).tolist() == [True]
    # the window: the keyframes of frames 2 and 4 seen from frame 5; over the last 2 frames only one
    assert DynamicLoop.stationary(loop(False, frames=2), depth, ids, np.eye(4)).tolist() == [False]
    # with the centre feature the window is half as long: 4 frames see one keyframe, 3 frames too few to judge
    assert DynamicLoop.stationary(loop(False, frames=4), depth, ids, np.eye(4)).tolist() == [True]
    assert DynamicLoop.stationary(loop(True, frames=4), depth, ids, np.eye(4)).tolist() == [False]
    assert DynamicLoop.stationary(loop(True, frames=3), depth, ids, np.eye(4)) is None


def test_forget_near_marks_keyframe_rays_on_a_departed_surface_for_good():
    from dynslam_cli.slam.keyframes import forget_near

    intr = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    pixels = np.array([[31, 23], [10, 10], [50, 40]], np.int32)  # (u, v): centre, top-left, bottom-right
    kf = Keyframe(0, 0.0, pixels, np.zeros((3, 3), np.uint8), np.array([1.0, 3.0, 3.0], np.float32),
                  np.zeros(3, np.int32), np.ones(3, bool), np.eye(4))
    left = np.array([[-0.01, 0.0, 1.0], [0.02, 0.01, 1.01]])  # the surface seen gone: the centre ray's point
    assert forget_near([kf], left, intr, 0.05) == 1
    assert kf.gone.tolist() == [True, False, False] and kf.usable.tolist() == [False, True, True]
    assert forget_near([kf], left, intr, 0.05) == 0  # already gone
    assert forget_near([kf], np.zeros((0, 3)), intr, 0.05) == 0


def test_forget_seen_through_marks_rays_a_later_view_sees_past():
    from dynslam_cli.slam.keyframes import forget_seen_through

    intr = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    # rays on a box at 1 m (centre), on the wall at 3 m (top-left) and on the box's edge pixel
    pixels = np.array([[31, 23], [10, 10], [40, 23]], np.int32)
    kf = Keyframe(0, 0.0, pixels, np.zeros((3, 3), np.uint8), np.array([1.0, 3.0, 1.0], np.float32),
                  np.zeros(3, np.int32), np.ones(3, bool), np.eye(4))
    now = np.full((48, 64), 3.0, np.float32)  # the box has gone: the wall behind it everywhere ...
    now[20:27, 41:48] = 0.0  # ... but for a hole right of the edge ray (within its 3 px window)
    assert forget_seen_through([kf], now, np.eye(4), intr, margin=0.3, window=3) == 1
    assert kf.gone.tolist() == [True, False, False] and kf.usable.tolist() == [False, True, True]
    assert forget_seen_through([kf], now, np.eye(4), intr, margin=0.3, window=3) == 0  # already gone
    # the box still there (same depth), or the view stopping within the margin: nothing goes
    kf2 = Keyframe(0, 0.0, pixels, np.zeros((3, 3), np.uint8), np.array([1.0, 3.0, 1.0], np.float32),
                   np.zeros(3, np.int32), np.ones(3, bool), np.eye(4))
    still = np.full((48, 64), 3.0, np.float32)
    still[15:32, 20:45] = 1.0
    assert forget_seen_through([kf2], still, np.eye(4), intr, margin=0.3) == 0
    assert forget_seen_through([kf2], np.full((48, 64), 1.2, np.float32), np.eye(4), intr, margin=0.3) == 0
    # a camera moved 0.5 m to the right sees the box's point at another pixel, through to the wall
    moved = np.eye(4)
    moved[0, 3] = 0.5
    assert forget_seen_through([kf2], np.full((48, 64), 3.0, np.float32), moved, intr, margin=0.3) == 2
    assert kf2.gone.tolist() == [True, False, True]


def test_forget_overtaken_marks_rays_whose_free_space_a_newcomer_fills():
    from dynslam_cli.slam.keyframes import forget_overtaken

    intr = SimpleNamespace(fx=50.0, fy=50.0, cx=31.5, cy=23.5)
    wall = np.full((48, 64), 3.0, np.float32)
    boxed = wall.copy()
    boxed[15:32, 20:45] = 1.5  # a box set down in front of the wall

    def keyframe(saw):
        # rays at the centre (behind where the box now stands) and at a corner, both on the wall
        return Keyframe(0, 0.0, np.array([[31, 23], [5, 5]], np.int32), np.zeros((2, 3), np.uint8),
                        np.array([3.0, 3.0], np.float32), np.zeros(2, np.int32), np.ones(2, bool), np.eye(4),
                        depth_raw_small=subsample_depth(saw))

    before = keyframe(wall)  # saw the wall through where the box now is: its centre ray is stale
    assert forget_overtaken([before], boxed, np.eye(4), intr, margin=0.3, step=2) == 1
    assert before.gone.tolist() == [True, False] and before.usable.tolist() == [False, True]
    assert forget_overtaken([before], boxed, np.eye(4), intr, margin=0.3, step=2) == 0  # already gone
    # a keyframe that saw the box there already (it did not arrive), or a wall that did not change
    assert forget_overtaken([keyframe(boxed)], boxed, np.eye(4), intr, margin=0.3, step=2) == 0
    assert forget_overtaken([keyframe(wall)], wall, np.eye(4), intr, margin=0.3, step=2) == 0
    # the box only 0.2 m in front of the wall: within the margin, nothing changes
    near = wall.copy()
    near[15:32, 20:45] = 2.8
    assert forget_overtaken([keyframe(wall)], near, np.eye(4), intr, margin=0.3, step=2) == 0
    # without the keyframe's raw depth there is nothing to judge
    bare = keyframe(wall)
    bare.depth_raw_small = None
    assert forget_overtaken([bare], boxed, np.eye(4), intr, margin=0.3, step=2) == 0
