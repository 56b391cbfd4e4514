"""The ground-truth-tracked backend and the pose-only solves of benchmarks/bench_pose_bias.py (the benchmark
itself is run by hand)."""

import numpy as np
import pytest

import benchmark_scripts  # tests/benchmark_scripts.py

B = benchmark_scripts.load("bench_pose_bias")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from dynslam_cli.synth.config import SynthConfig
    from dynslam_cli.synth.render import render_preset

    out = tmp_path_factory.mktemp("pose_bias") / "static"
    render_preset("static", out, SynthConfig(depth_noise=0.0, depth_holes=0.0), frames=12, progress=False)
    return out


@pytest.fixture(scope="module")
def built(scene):
    """The ground-truth-tracked backend over the scene, built once (the solves only read it)."""
    return B.ground_truth_backend(str(scene), 0.002)


class TestGroundTruthBackend:
    def test_keyframes_sit_at_the_true_poses(self, built):
        be, seq, gt, depths = built
        assert len(seq) == 12 and len(depths) == 12 and len(be.kf_frame) >= 1
        for f, pose in zip(be.kf_frame, be.kf_pose, strict=False):
            # the bundle adjustments may move them a little; the tracked poses were the truth
            assert np.linalg.norm(pose[:3, 3] - gt[int(f)][:3, 3]) < 0.01
        assert np.allclose(gt[0], np.eye(4))

    def test_tracked_poses_are_the_truth_and_the_backend_is_restored(self, built):
        import dynslam_cli.backend.backend as bk
        from dynslam_cli.backend import tracking

        be, _, gt, _ = built
        traj = be.trajectory()
        last = len(traj) - 1
        if last not in set(int(f) for f in be.kf_frame):  # a keyframe's pose is the bundle adjustment's
            assert np.allclose(traj[last], gt[last], atol=1e-6)
        assert bk.track_frame is tracking.track_frame
        assert bk.Backend._fuse.__name__ == "_fuse"


class TestSolveBias:
    def test_solves_land_near_the_truth_and_report_the_kernel(self, built):
        be, _, gt, depths = built
        r = B.solve_bias(be, gt, depths, 2.8)
        assert r["frames"] >= 5 and r["matches"] > 100 * r["frames"]
        assert np.abs(r["mean"]).max() < 5.0  # mm: a right map, a solve from the truth
        assert 0 <= r["beyond"] < 0.2 * r["matches"] and r["outliers"].shape == (r["beyond"], 6)
        wide = B.solve_bias(be, gt, depths, 1e6)
        assert wide["beyond"] == 0 and wide["matches"] == r["matches"]


class TestDepthSkew:
    def test_bins_cover_every_match_within_5_cm(self, built):
        be, _, gt, _ = built
        rows = B.depth_skew(be, gt)
        assert [q["hi"] for q in rows] == list(B.SLOPE_BINS)
        assert sum(q["n"] for q in rows) > 100 and 0.5 < sum(q["share"] for q in rows) <= 1.0 + 1e-9
        for q in rows:
            if q["n"]:
                assert abs(q["mean"]) < 50 and abs(q["median"]) < 50

    def test_landmarks_on_the_observations_give_zero(self, built):
        """A frame's matched landmarks moved onto what it observes at its true pose: every difference is 0."""
        be, _, gt, _ = built
        row = max(be.matches.frames())
        ids, kp = be.matches.get(row)
        ok = (ids >= 0) & (kp.depth > 0)
        d = kp.depth[ok]
        pc = np.c_[(kp.uv[ok, 0] - be.cam.cx) / be.cam.fx * d, (kp.uv[ok, 1] - be.cam.cy) / be.cam.fy * d, d]
        saved = be.lm.pos.copy()  # the fixture is shared: put the landmarks back
        try:
            be.lm.pos[ids[ok]] = pc @ gt[row][:3, :3].T + gt[row][:3, 3]
            rows = B.depth_skew(be, gt, frames=[row])
        finally:
            be.lm.pos = saved
        assert sum(q["n"] for q in rows) > 20
        for q in rows:
            if q["n"]:
                assert abs(q["mean"]) < 1e-6 and abs(q["median"]) < 1e-6


class TestCreatedMap:
    def test_no_bundle_keeps_each_landmark_where_its_keyframe_saw_it(self, scene):
        import dynslam_cli.backend.backend as bk

        real = bk.local_bundle_adjustment
        be, _, _, _ = B.ground_truth_backend(str(scene), 0.002, bundle=False)
        assert bk.local_bundle_adjustment is real
        first = {}
        for j, kf, d in zip(be.lm.obs_lm, be.lm.obs_kf, be.lm.obs_depth, strict=True):
            first.setdefault(int(j), (int(kf), float(d)))
        checked = 0
        for j, (kf, d) in first.items():
            if d <= 0 or int(be.lm.first_kf[j]) != kf:
                continue
            T = be.kf_pose[kf]
            assert ((be.lm.pos[j] - T[:3, 3]) @ T[:3, :3])[2] == pytest.approx(d, abs=1e-9)
            checked += 1
        assert checked > 50
