import json

import numpy as np
import pytest
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.run.runner import select_device
from dynslam_cli.slam.toyscene import write_sequence
from tiny_runs import read_traj as _traj

TINY = ["--set", "map.n_levels=4", "--set", "map.log2_hashmap_size=12",
        "--set", "map.voxel_size=0.1", "--set", "mapping.first_iters=15",
        "--set", "tracking.iters=3", "--set", "tracking.n_rays=128", "--set", "mapping.iters=3",
        "--set", "mapping.n_rays=256", "--set", "tracking.ignore_border=2", "--set", "run.threads=1",
        "--set", "run.mesh_resolution=0.1", "--set", "mapping.every=2", "--set", "mapping.keyframe_every=2"]


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return write_sequence(tmp_path_factory.mktemp("clip") / "toybox", n=6, width=80, height=60)


def _run(args):
    return CliRunner().invoke(app, args)


def _proc_status_mb(key: str) -> float:
    """A memory line of /proc/self/status (VmRSS: now, VmHWM: peak so far; kB there) in MiB."""
    with open("/proc/self/status") as f:
        return next(int(ln.split()[1]) for ln in f if ln.startswith(key + ":")) / 1024.0


def test_run_writes_the_run_folder(clip, tmp_path):
    out = tmp_path / "run"
    rss_before = _proc_status_mb("VmRSS")  # the run is in this process: its peak is at least this
    res = _run(["run", "--seq", str(clip), "--mode", "static", "--out", str(out), "-q"] + TINY)
    assert res.exit_code == 0, res.output
    for name in ("config.yaml", "run.json", "traj_est.txt", "mesh.ply", "timing.json"):
        assert (out / name).is_file(), name
    meta = json.loads((out / "run.json").read_text())
    assert meta["status"] == "completed" and meta["mode"] == "static" and meta["frames"] == 6
    assert meta["sequence"]["groundtruth"].endswith("groundtruth.txt") and meta["device"] == str(select_device("auto"))
    # the numba layer the kernels really ran on, not the one asked for before any kernel ran
    assert meta["versions"]["numba_threading_layer"] in ("workqueue", "omp", "tbb")
    for lib in ("opencv", "onnxruntime", "openvino", "gtsam", "scipy", "cpu"):  # what else a trajectory depends on
        assert meta["versions"][lib], lib
    traj = _traj(out / "traj_est.txt")
    assert traj.shape == (6, 8)
    stamps = [ln.split()[0] for ln in (clip / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    assert np.allclose(traj[:, 0], [float(s) for s in stamps])
    assert np.allclose(np.linalg.norm(traj[:, 4:], axis=1), 1, atol=1e-5)
    # the backend's trajectory before its centres were smoothed, beside it (6 frames: too few to smooth)
    assert np.array_equal(_traj(out / "traj_unsmoothed.txt"), traj)
    online = _traj(out / "traj_online.txt")  # each frame's pose as it was when the frame was done
    assert online.shape == (6, 8) and np.allclose(online[:, 0], traj[:, 0]) and np.allclose(online[0], traj[0])
    rows = [json.loads(ln) for ln in (out / "frames.jsonl").read_text().splitlines()]  # how each frame was tracked
    assert [r["frame"] for r in rows] == list(range(6)) and [r["timestamp"] for r in rows] == stamps
    assert all(r["tracked"].startswith(("first", "motion", "wide", "relocalised")) and r["inliers"] > 0
               or "lost" in r["events"] or r["tracked"].startswith("lost") for r in rows)  # this clip is tiny: lost
    timing = json.loads((out / "timing.json").read_text())
    assert timing["frames"] == 6 and timing["fps"] > 0 and "track" in timing["median_ms"]
    assert set(timing["smoothing"]) == {"q_m2_s3", "noise_sd_m", "downweighted_frames", "refined_frames"}
    assert 0 <= timing["smoothing"]["refined_frames"] < 6  # frames solved again against the final map
    # calls: frames each part ran on (tracking every frame; mapping on frame 0 and every keyframe_every-th)
    assert timing["calls"]["track"] == 6 and timing["calls"]["frame"] == 6 and 1 <= timing["calls"]["map"] < 6
    assert isinstance(timing["peak_rss_mb"], float) and 0 < rss_before <= timing["peak_rss_mb"] <= _proc_status_mb("VmHWM")
    assert timing["cpu_ms_per_frame"] > 0  # every thread's CPU time while the frames ran
    assert (out / "mesh.ply").read_bytes()[:3] == b"ply" and b"binary" in (out / "mesh.ply").read_bytes()[:200]
    assert not (out / "checkpoint.pt").exists()


def test_resume_gives_the_same_trajectory(clip, tmp_path):
    full = tmp_path / "full"
    part = tmp_path / "part"
    args = ["run", "--seq", str(clip), "--mode", "static", "-q", "--set", "run.mesh=false",
            "--set", "mapping.final_iters=3"] + TINY  # the final bundle adjustment runs after a resume too
    assert _run(args + ["--out", str(full)]).exit_code == 0
    assert json.loads((full / "timing.json").read_text())["final_ba_ms"] > 0
    res = _run(args + ["--out", str(part), "--stop-after", "3"])
    assert res.exit_code == 0 and "--resume" in res.output
    assert json.loads((part / "run.json").read_text())["status"] == "interrupted"
    assert (part / "checkpoint.pt").is_file() and not (part / "traj_est.txt").exists()
    res = _run(args + ["--out", str(part), "--stop-after", "3", "--resume"])
    assert res.exit_code == 0, res.output
    assert json.loads((part / "run.json").read_text())["status"] == "completed"
    assert np.allclose(_traj(full / "traj_est.txt"), _traj(part / "traj_est.txt"), atol=1e-6)
    assert np.allclose(_traj(full / "traj_online.txt"), _traj(part / "traj_online.txt"), atol=1e-6)
    assert (full / "frames.jsonl").read_text() == (part / "frames.jsonl").read_text()  # the rows before the stop kept


def test_bad_input_exits_2_with_one_line(clip, tmp_path):
    res = _run(["run", "--seq", str(tmp_path / "missing"), "--mode", "static", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and res.output.strip().startswith("error:") and len(res.output.strip().splitlines()) == 1
    res = _run(["run", "--seq", str(clip), "--mode", "moving", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "--mode must be static or dynamic" in res.output
    res = _run(["run", "--seq", str(clip), "--mode", "static", "--out", str(tmp_path / "o"), "--set", "tracking.iterz=3"])
    assert res.exit_code == 2 and "unknown config key 'tracking.iterz'" in res.output
    res = _run(["run", "--seq", str(clip), "--mode", "static", "--out", str(tmp_path / "o"), "--device", "tpu"])
    assert res.exit_code == 2 and "device" in res.output and "'tpu'" in res.output
    res = _run(["run", "--seq", str(clip), "--mode", "static", "--out", str(tmp_path / "o2"), "--resume"])
    assert res.exit_code == 2 and "checkpoint" in res.output


@pytest.mark.parametrize("exc, status", [(RuntimeError("injected fault"), "failed"),
                                         (KeyboardInterrupt(), "interrupted")])
def test_a_run_that_breaks_says_so_and_frees_the_folder(clip, tmp_path, monkeypatch, exc, status):
    from dynslam_cli.slam.system import SLAM

    track = SLAM.track

    def breaks_at_frame_2(self, frame, *a, **k):
        if frame.index == 2:
            raise exc
        return track(self, frame, *a, **k)

    monkeypatch.setattr(SLAM, "track", breaks_at_frame_2)
    out = tmp_path / "run"
    res = _run(["run", "--seq", str(clip), "--mode", "static", "--out", str(out), "-q"] + TINY)
    assert res.exit_code != 0
    meta = json.loads((out / "run.json").read_text())
    assert meta["status"] == status and meta["finished"]
    assert ("injected fault" in meta["error"]) if status == "failed" else ("interrupted" in meta["error"])
    assert not (out / ".lock").exists() and not (out / "traj_est.txt").exists()


def test_run_json_says_completed_only_after_the_mesh(clip, tmp_path, monkeypatch):
    from dynslam_cli.slam.system import SLAM

    out = tmp_path / "run"
    seen = []

    def mesh_fails(self, voxel):
        seen.append(json.loads((out / "run.json").read_text())["status"])
        raise MemoryError("marching cubes ran out of memory")

    monkeypatch.setattr(SLAM, "extract_mesh", mesh_fails)
    res = _run(["run", "--seq", str(clip), "--mode", "static", "--out", str(out), "-q"] + TINY)
    assert res.exit_code != 0 and seen == ["running"]
    meta = json.loads((out / "run.json").read_text())
    assert meta["status"] == "failed" and "MemoryError: marching cubes" in meta["error"]
    assert not (out / "mesh.ply").exists() and not (out / "timing.json").exists()


def test_progress_phases_on_stderr_and_threads(clip, tmp_path):
    out = tmp_path / "run"
    res = _run(["run", "--seq", str(clip), "--mode", "static", "--out", str(out)] + TINY + ["--threads", "2"])
    assert res.exit_code == 0, res.output
    err = res.stderr
    init = err.index("initialising the map from frame 0 (15 iterations)...")
    assert init < err.index("1/6") < err.index("6/6") < err.index("extracting the mesh (0.1 m voxels)...")
    assert "0/6" not in err  # the bar starts once frame 0 has initialised the map
    assert res.stdout.startswith("run completed: 6 frames")
    assert json.loads((out / "run.json").read_text())["threads"] == 2
    res = _run(["run", "--seq", str(clip), "--mode", "static", "--out", str(out), "-q", "--overwrite"] + TINY)
    assert res.exit_code == 0 and res.stderr == ""
    res = _run(["run", "--seq", str(clip), "--mode", "static", "--out", str(out), "--threads", "-1"] + TINY)
    assert res.exit_code == 2 and "--threads must be >= 0" in res.output
