"""The per-frame loop of both modes (``run/loop.py``): static mode is SLAM.process frame by frame; dynamic mode
end to end (the motion module wired into it); the motion module's pieces are tested beside their modules
(test_motion_module, test_motion_checkable, test_motion_stayed, test_motion_forget)."""

import json

import numpy as np
from typer.testing import CliRunner

from dynslam_cli.cli import app
from tiny_runs import early_check, read_traj as _traj, tiny_sets, walker_fixture  # noqa: F401 (early_check: an autouse fixture)

TINY = tiny_sets()


walker = walker_fixture(96, 72, 10)


class TestFrameLoop:
    def test_static_mode_is_slam_process_frame_by_frame(self):
        import torch

        from dynslam_cli.run.loop import TIMED, FrameLoop
        from dynslam_cli.slam.system import SLAM
        from dynslam_cli.slam.toyscene import TinyIntrinsics, ToyFrame, tiny_config, trajectory

        intr = TinyIntrinsics(48, 36, f=20.0)
        cfg = tiny_config(**{"run.mode": "static", "mapping.first_iters": 10, "tracking.iters": 2,
                             "mapping.iters": 2, "mapping.every": 2, "mapping.keyframe_every": 2})
        frames = [ToyFrame(i, p, intr) for i, p in enumerate(trajectory(4, step=0.01))]
        torch.set_num_threads(1)
        ref = SLAM(cfg, intr, torch.device("cpu"))
        for f in frames:
            ref.process(f)
        slam = SLAM(cfg, intr, torch.device("cpu"))
        loop = FrameLoop(cfg, intr, slam, torch.device("cpu"))
        assert loop.mm is None
        steps = [loop.process(f, str(f.index)) for f in frames]
        assert all(set(TIMED) <= set(s) and s["segment"] == 0.0 and s["frame"] > 0 for s in steps)
        assert np.array_equal(slam.trajectory(), ref.trajectory()) and len(slam.keyframes) == len(ref.keyframes)
        mesh, dropped = loop.mesh(0.05)  # static mode forgets nothing, in the mesh neither
        assert dropped == 0 and np.array_equal(mesh.vertices, slam.extract_mesh(0.05).vertices)
        state = loop.state_dict()
        assert state["motion"] is None and state["records"] == [] and [r["frame"] for r in state["frames"]] == [0, 1, 2, 3]


    def test_the_mesh_is_judged_tighter_near_a_departed_place(self, monkeypatch):
        import torch

        from dynslam_cli.motion import forget
        from dynslam_cli.run.loop import FrameLoop
        from dynslam_cli.slam.system import SLAM
        from dynslam_cli.slam.toyscene import TinyIntrinsics, ToyFrame, tiny_config, trajectory

        intr = TinyIntrinsics(48, 36, f=20.0)
        cfg = tiny_config(**{"run.mode": "dynamic", "motion.encoder": "color-hist", "mapping.first_iters": 10,
                             "tracking.iters": 2, "mapping.iters": 2, "mapping.every": 2, "mapping.keyframe_every": 2})
        monkeypatch.setattr("dynslam_cli.run.loop.CHECK_WARMUP", 10)  # toy frames are not checked
        torch.set_num_threads(1)
        slam = SLAM(cfg, intr, torch.device("cpu"))
        loop = FrameLoop(cfg, intr, slam, torch.device("cpu"))
        for f in [ToyFrame(i, p, intr) for i, p in enumerate(trajectory(3, step=0.01))]:
            loop.process(f, str(f.index))
        margins = []

        def spy(points, keyframes, intr, margin, **k):
            margins.append(np.broadcast_to(margin, (len(points),)).copy())
            return forget.departed_surface(points, keyframes, intr, margin, **k)

        monkeypatch.setattr("dynslam_cli.run.loop.departed_surface", spy)
        verts = np.asarray(loop.mesh(0.05)[0].vertices)
        t_d, radius, tr = cfg.motion.depth_threshold, cfg.run.forget_radius, slam.model.truncation
        assert radius < tr and np.all(margins[0] == tr)  # nothing was seen to leave: the truncation everywhere
        mesh = slam.extract_mesh(0.05)
        loop.departed.add(np.asarray(mesh.vertices)[:1])  # something left at the first vertex
        loop.mesh(0.05)
        near = np.linalg.norm(np.asarray(mesh.vertices) - (np.floor(mesh.vertices[0] / loop.departed.CELL) + 0.5)
                              * loop.departed.CELL, axis=1) <= t_d
        assert near.any() and not near.all() and len(verts) == len(mesh.vertices)
        assert np.array_equal(margins[1], np.where(near, radius, tr))
        state = loop.state_dict()
        again = FrameLoop(cfg, intr, slam, torch.device("cpu"))
        again.load_state_dict(state)  # the departed places come back with a checkpoint
        assert np.array_equal(again.departed.state(), loop.departed.state())
        again.load_state_dict({k: v for k, v in state.items() if k != "departed"})  # one from before them
        assert len(again.departed) == 0


def test_dynamic_run_writes_masks_updates_and_timing(walker, tmp_path, monkeypatch):
    monkeypatch.setattr("dynslam_cli.run.loop.RETRACK_FRACTION", 0.0001)
    from dynslam_cli.motion import forget

    departed = []

    def spy(*a, **k):  # what the mesh leaves out as seen through
        out = forget.departed_surface(*a, **k)
        departed.append(int(out.sum()))
        return out

    monkeypatch.setattr("dynslam_cli.run.loop.departed_surface", spy)
    out = tmp_path / "dyn"
    res = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "dynamic", "--out", str(out),
                                   "--save-masks", "-q"] + TINY)
    assert res.exit_code == 0, res.output
    meta = json.loads((out / "run.json").read_text())
    assert meta["status"] == "completed" and meta["mode"] == "dynamic"
    assert meta["encoder"] == "color-hist on numpy"  # what computed the embeddings (runtimes round differently)
    stamps = [ln.split()[0] for ln in (walker / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    masks = sorted(p.stem for p in (out / "masks").glob("*.png"))
    assert masks == sorted(stamps)
    renders = sorted(p.name for p in (out / "renders").glob("*_depth.png"))
    assert renders and all(r[: -len("_depth.png")] in stamps for r in renders)
    timing = json.loads((out / "timing.json").read_text())
    for k in ("segment", "encode", "track", "render", "check", "update", "judge", "keyframes", "map", "frame"):
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
    rows = [json.loads(ln) for ln in (out / "frames.jsonl").read_text().splitlines()]  # one per frame
    assert [r["frame"] for r in rows] == list(range(10)) and [r["timestamp"] for r in rows] == stamps
    assert {r["frame"] for r in rows if r["checked"]} == {int(r[: -len("_depth.png")] in stamps) * stamps.index(
        r[: -len("_depth.png")]) for r in renders}  # the checked frames are those with a rendered view
    assert {r["frame"] for r in rows if r["retracked"]} == {r["frame"] for r in recs if r["retracked"]}
    masked = {p.stem: (np.asarray(__import__("PIL.Image", fromlist=["Image"]).open(p)) > 0).mean()
              for p in (out / "masks").glob("*.png")}
    assert all(abs(r["dynamic_pixels"] - masked[r["timestamp"]]) < 1e-5 for r in rows)
    assert isinstance(timing["keyframe_rays_gone"], int) and timing["keyframe_rays_gone"] >= 0
    assert len(departed) == 1 and timing["mesh_vertices_departed"] == departed[0]
    assert _traj(out / "traj_est.txt").shape == (10, 8)


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


def test_dynamic_run_at_two_threads_equals_the_frames_in_order(walker, tmp_path):
    """With a second core the run segments and encodes each next frame beside the current one
    (run/ahead.py); the trajectory and the classifier's updates are those of the frames in order."""
    import torch

    from dynslam_cli.config.loader import config_from_file
    from dynslam_cli.data.open import open_sequence
    from dynslam_cli.run.loop import FrameLoop
    from dynslam_cli.run.runner import sequence_bounds
    from dynslam_cli.slam.system import SLAM
    from dynslam_cli.utils.threads import seed_everything, set_threads

    out = tmp_path / "ahead"
    res = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "dynamic", "--out", str(out), "-q"]
                             + tiny_sets(threads=2))
    assert res.exit_code == 0, res.output
    timing = json.loads((out / "timing.json").read_text())
    assert timing["mean_ms"]["encode"] > 0 and "wait" in timing["mean_ms"]
    cfg = config_from_file(out / "config.yaml")
    old = torch.get_num_threads()
    try:
        set_threads(2)
        seed_everything(int(cfg.run.seed))
        seq = open_sequence(str(walker), cfg, progress=False)
        slam = SLAM(cfg, seq.intrinsics, torch.device("cpu"), bounds=sequence_bounds(cfg, seq),
                    depth_noise=seq.depth_noise)
        loop = FrameLoop(cfg, seq.intrinsics, slam, torch.device("cpu"))
        for i in range(len(seq)):
            loop.process(seq[i], seq.stamps[i])
        traj, _ = slam.final_trajectory()
    finally:
        torch.set_num_threads(old)
    assert np.allclose(_traj(out / "traj_unsmoothed.txt")[:, 1:4], traj[:, :3, 3], atol=1e-6)
    assert np.allclose(_traj(out / "traj_online.txt")[:, 1:4], np.array(slam.online)[:, :3, 3], atol=1e-6)
    updates = [json.loads(ln) for ln in (out / "classifier_updates.jsonl").read_text().splitlines()]
    assert [u["labels"] for u in updates] == [r["labels"] for r in loop.records]


def test_dynamic_run_checks_every_nth_frame(walker, tmp_path):
    """motion.check_every=2: the check (its render, written beside the masks) runs on every 2nd frame after the
    warm-up; the classifier still labels every frame (a mask per frame)."""
    from dynslam_cli.run.loop import CHECK_WARMUP

    out = tmp_path / "every2"
    res = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "dynamic", "--out", str(out), "-q",
                                   "--save-masks", "--set", "motion.check_every=2"] + TINY)
    assert res.exit_code == 0, res.output
    stamps = [ln.split()[0] for ln in (walker / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    assert sorted(p.stem for p in (out / "masks").glob("*.png")) == sorted(stamps)
    checked = sorted(stamps.index(p.name[: -len("_depth.png")]) for p in (out / "renders").glob("*_depth.png"))
    assert checked == [i for i in range(len(stamps)) if i >= CHECK_WARMUP and i % 2 == 0]
    for ln in (out / "classifier_updates.jsonl").read_text().splitlines():
        assert json.loads(ln)["frame"] in checked


def test_dynamic_run_maps_with_the_mask_from_before_the_check(walker, tmp_path, monkeypatch):
    """The map and the backend's keyframe are given the frame's static mask from before its check (what the check
    finds reaches the keyframe at the next classifier update): here every check newly masks the left quarter."""
    from dynslam_cli.motion.module import MotionModule
    from dynslam_cli.slam.system import SLAM

    before_check, mapped = {}, {}
    check, map_ = MotionModule.check_and_update, SLAM.map

    def check_masking_more(self, frame, inst, *a, **k):
        before_check[inst.frame_index] = inst.static_mask.copy()
        record = check(self, frame, inst, *a, **k)
        mask = inst.static_mask.copy()
        mask[:, : mask.shape[1] // 4] = False
        inst.static_mask = mask
        return record

    def spy_map(self, frame, mask=None, instance_ids=None):
        mapped[self.n_frames - 1] = None if mask is None else np.asarray(mask).copy()
        return map_(self, frame, mask, instance_ids)

    monkeypatch.setattr(MotionModule, "check_and_update", check_masking_more)
    monkeypatch.setattr(SLAM, "map", spy_map)
    res = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "dynamic", "--out", str(tmp_path / "d"),
                                   "-q"] + TINY)
    assert res.exit_code == 0, res.output
    assert len(before_check) >= 5
    assert all(np.array_equal(mapped[i], m) and m[:, 0].any() for i, m in before_check.items())


def test_frames_jsonl_says_how_the_backend_tracked_each_frame(tmp_path_factory, tmp_path):
    """frames.jsonl on a clip large enough for the backend's keypoints: the first frame starts the map, the
    others are tracked by the motion model's guess with static inliers, keyframes named where they fell due."""
    from tiny_runs import render_walker

    walker = render_walker(tmp_path_factory, 320, 240, 5)
    out = tmp_path / "s"
    res = CliRunner().invoke(app, ["run", "--seq", str(walker), "--mode", "static", "--out", str(out), "-q"] + TINY)
    assert res.exit_code == 0, res.output
    rows = [json.loads(ln) for ln in (out / "frames.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in rows] == list(range(5)) and rows[0]["tracked"] == "first"
    assert all(r["tracked"].split(";")[0] in ("motion", "wide", "relocalised") and r["inliers"] >= 20 and
               not r["events"] for r in rows[1:])
    assert "retracked" not in rows[0] and "dynamic_pixels" not in rows[0]  # static mode: no motion module


def test_this_frames_events_reads_only_the_frame_asked():
    from dynslam_cli.run.loop import this_frames_events

    events = [{"frame": 2, "kind": "lost"}, {"frame": 5, "kind": "guess_rejected"}, {"frame": 5, "kind": "lost"}]
    assert this_frames_events(events, 5) == ["guess_rejected", "lost"]
    assert this_frames_events(events, 2) == ["lost"] and this_frames_events(events, 3) == []
    assert this_frames_events([], 0) == []
