"""Sequence readers on the real frames in ../shared and on generated folders."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_data_helpers import data_cfg, make_folder, quat_z

from dynslam_cli.config import load_config
from dynslam_cli.data.open import open_sequence
from dynslam_cli.data.types import Frame, Intrinsics
from dynslam_cli.errors import DynslamError

BONN_K = [542.822841, 542.576870, 315.593520, 237.756098]


def _first_data_line(path: Path) -> list[str]:
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            return line.split()
    raise AssertionError(f"no data in {path}")


# -------------------------------------------------------------------------- real Bonn clip
def test_bonn_clip(bonn_clip: Path):
    seq = open_sequence(str(bonn_clip))
    assert seq.dataset == "bonn" and len(seq) == 150
    assert seq.intrinsics.as_list() == pytest.approx(BONN_K)
    assert (seq.intrinsics.width, seq.intrinsics.height) == (640, 480)
    assert seq.distortion[:4] == pytest.approx([0.039903, -0.099343, -0.000730, -0.000144])
    assert seq.undistorted
    assert seq.groundtruth_file == bonn_clip / "groundtruth.txt"
    assert not seq.has_gt_masks
    ts = seq.timestamps
    assert ts.shape == (150,) and np.all(np.diff(ts) > 0)
    assert ts[0] == pytest.approx(float(_first_data_line(bonn_clip / "rgb.txt")[0]), abs=1e-6)
    assert 9.0 < ts[-1] - ts[0] < 11.0  # every 2nd pair of 30 Hz: ~15 Hz
    poses = seq.gt_poses
    assert sum(p is not None for p in poses) == 150
    for k in (0, 75, 149):
        f = seq[k]
        assert isinstance(f, Frame) and f.index == k and f.timestamp == ts[k]
        assert f.rgb.dtype == np.uint8 and f.rgb.shape == (480, 640, 3)
        assert f.depth.dtype == np.float32 and f.depth.shape == (480, 640)
        valid = f.depth[f.depth > 0]
        # configs/bonn.yaml cuts depth at data.max_depth = 3.178 m (3 m as read; the far wall's depth is warped)
        assert valid.size > 0.25 * f.depth.size
        assert 0.3 < valid.min() and valid.max() <= 3.178 and 1.0 < np.median(valid) < 3.178
        R = f.pose_c2w[:3, :3]
        assert f.pose_c2w.dtype == np.float64
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) == pytest.approx(1.0)
        assert f.instance_ids is None and f.dynamic_mask is None
    assert seq[-1].index == 149


def test_bonn_gt_is_interpolated_between_neighbours(bonn_clip: Path):
    from dynslam_cli.data.tum import read_trajectory

    seq = open_sequence(str(bonn_clip), load_config("bonn", "crowd", overrides=["data.frames=5"]))
    gt_t, gt_T = read_trajectory(bonn_clip / "groundtruth.txt")
    for t, T in zip(seq.timestamps, seq.gt_poses, strict=False):
        k = np.searchsorted(gt_t, t)
        a = (t - gt_t[k - 1]) / (gt_t[k] - gt_t[k - 1])
        assert 0 < a < 1
        assert np.allclose(T[:3, 3], (1 - a) * gt_T[k - 1][:3, 3] + a * gt_T[k][:3, 3], atol=1e-9)


def test_bonn_max_depth_and_cut(bonn_clip: Path):
    cfg = load_config("bonn", "bonn_crowd_150_449_s2", overrides=[
        "data.start=10", "data.frames=4", "data.stride=3", "data.max_depth=2.8"])
    seq = open_sequence(str(bonn_clip), cfg)
    full = open_sequence(str(bonn_clip))
    assert len(seq) == 4
    assert np.array_equal(seq.timestamps, full.timestamps[[10, 13, 16, 19]])
    f, ref = seq[1], full[13].depth
    assert f.index == 1 and f.timestamp == full.timestamps[13]
    assert np.array_equal(f.depth, np.where(ref > 2.8, 0.0, ref))
    assert (f.depth > 0).any() and (ref > 2.8).any()


# -------------------------------------------------------------------------- real TUM frames
def test_tum_frames_with_associations(tum_clip: Path):
    seq = open_sequence(str(tum_clip))
    assert seq.dataset == "tum" and len(seq) == 9
    assert seq.intrinsics.as_list() == pytest.approx([517.3, 516.5, 318.6, 255.3])
    assert seq.undistorted  # fr1 has non-zero distortion in configs/tum.yaml
    assoc = [ln.split() for ln in (tum_clip / "associations.txt").read_text().splitlines() if ln.strip()]
    assert np.allclose(seq.timestamps, [float(a[0]) for a in assoc])
    assert seq.stamps == [a[0] for a in assoc]
    assert [r.depth.name for r in seq.records] == [Path(a[3]).name for a in assoc]
    assert all(p is not None for p in seq.gt_poses)
    # full ground truth at 100 Hz: each pose lies between neighbouring samples
    from dynslam_cli.data.tum import read_trajectory

    gt_t, gt_T = read_trajectory(seq.groundtruth_file)
    assert gt_t.size == 2335
    t0, T0 = seq.timestamps[0], seq.gt_poses[0]
    k = np.searchsorted(gt_t, t0)
    lo, hi = np.minimum(gt_T[k - 1][:3, 3], gt_T[k][:3, 3]), np.maximum(gt_T[k - 1][:3, 3], gt_T[k][:3, 3])
    assert np.all(T0[:3, 3] >= lo - 1e-9) and np.all(T0[:3, 3] <= hi + 1e-9)
    f = seq[4]
    valid = f.depth[f.depth > 0]
    assert 0.3 < np.median(valid) < 4.0 and f.rgb.shape == (480, 640, 3)


def test_tum_zero_distortion_gives_raw_pixels(tum_clip: Path):
    import cv2

    cfg = load_config("tum", "tum_fr1_desk_9", overrides=["data.distortion=[0, 0, 0, 0, 0]", "data.frames=1"])
    seq = open_sequence(str(tum_clip), cfg)
    assert not seq.undistorted
    raw = cv2.imread(str(seq.records[0].depth), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(seq[0].depth, raw.astype(np.float32) / 5000.0)
    rgb_raw = cv2.imread(str(seq.records[0].rgb))[:, :, ::-1]
    assert np.array_equal(seq[0].rgb, rgb_raw)


# -------------------------------------------------------------------------- generated folders
def test_generic_folder_lazy_decode_and_cut(tmp_path: Path):
    d = make_folder(tmp_path / "seq", n=6)
    cfg = data_cfg(intrinsics=[30.0, 31.0, 16.0, 12.0], start=1, frames=3, stride=2)
    seq = open_sequence(str(d), cfg)
    assert seq.dataset == "tum" and seq.name == "seq" and len(seq) == 3
    assert seq.intrinsics == Intrinsics(30.0, 31.0, 16.0, 12.0, 32, 24)
    assert np.allclose(seq.timestamps, [0.1, 0.3, 0.5])
    # lazy: removing an image after open fails only when that frame is read
    (d / "rgb" / "0.500000.png").unlink()
    f = seq[1]
    assert f.index == 1 and tuple(f.rgb[0, 0]) == (3, 0, 255)  # RGB order, source frame 3
    assert f.depth[1, 1] == 0.0 and f.depth[5, 2] == pytest.approx(1.3) and f.depth[5, 30] == pytest.approx(3.0)
    assert np.allclose(f.pose_c2w[:3, 3], [0.3, 0, 0])
    with pytest.raises(DynslamError, match=r"0\.500000\.png.*frame 2"):
        seq[2]
    with pytest.raises(IndexError):
        seq[3]
    import itertools

    assert [fr.index for fr in itertools.islice(seq, 2)] == [0, 1]


def test_gt_missing_frames_get_none(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=5, gt_ts=[0.0, 0.1, 0.4])
    seq = open_sequence(str(d), data_cfg(intrinsics=[30, 30, 16, 12]))
    assert [p is not None for p in seq.gt_poses] == [True, True, False, False, True]


def test_gt_interpolation_rotation_and_translation(tmp_path: Path):
    # ground truth at 0.00 and 0.03, an rgb frame at 0.01: interpolated at 1/3
    d = make_folder(tmp_path / "s", n=1, rgb_ts=[0.01], gt_ts=[0.0, 0.03])
    seq = open_sequence(str(d), data_cfg(intrinsics=[30, 30, 16, 12]))
    T = seq.gt_poses[0]
    assert T[0, 3] == pytest.approx(0.01)
    from dynslam_cli.data.tum import quat_to_matrix

    assert np.allclose(T[:3, :3], quat_to_matrix(quat_z(0.01)), atol=1e-9)
    # neighbours too far apart (gap 0.1 > 2·0.02): nearest sample within max diff
    d2 = make_folder(tmp_path / "s2", n=1, rgb_ts=[0.01], gt_ts=[0.0, 0.1])
    assert open_sequence(str(d2), data_cfg(intrinsics=[30, 30, 16, 12])).gt_poses[0][0, 3] == pytest.approx(0.0)


def test_synthetic_folder_masks_and_json_intrinsics(tmp_path: Path):
    d = make_folder(tmp_path / "walker_32x24", n=3, synth={"intrinsics": [40.0, 40.0, 15.5, 11.5]},
                    masks=True, depth_scale=1000.0)
    from dynslam_cli.data.names import identify

    assert identify(str(d)).dataset == "synth"
    seq = open_sequence(str(d))
    assert seq.dataset == "synth" and seq.has_gt_masks and seq.has_instances
    assert seq.intrinsics.as_list() == [40.0, 40.0, 15.5, 11.5]
    assert seq.depth_scale == 1000.0 and not seq.undistorted
    f = seq[2]
    assert f.instance_ids.dtype == np.int32 and f.instance_ids.shape == (24, 32)
    assert set(np.unique(f.instance_ids)) == {0, 3, 702}
    assert f.dynamic_mask.dtype == np.bool_ and f.dynamic_mask.sum() == 12 * 16
    assert np.array_equal(f.dynamic_mask, f.instance_ids == 702)
    assert f.depth[5, 2] == pytest.approx(1.2)  # depth / synth.json's 1000, not 5000
    from dynslam_cli.data.config import DataConfig

    assert seq.depth_noise == DataConfig.DEPTH_NOISE  # synth.json without a sensor block: the default


def test_synthetic_folder_tells_its_depth_noise(tmp_path: Path):
    from dynslam_cli.errors import DynslamError

    d = make_folder(tmp_path / "s", n=2, synth={"intrinsics": [40.0, 40.0, 15.5, 11.5],
                                                 "sensor": {"depth_noise": 0.002}})
    assert open_sequence(str(d)).depth_noise == 0.002
    d0 = make_folder(tmp_path / "s0", n=2, synth={"intrinsics": [40.0, 40.0, 15.5, 11.5], "sensor": {"depth_noise": 0}})
    assert open_sequence(str(d0)).depth_noise == 1e-4  # noiseless: trusted to the quantisation
    bad = make_folder(tmp_path / "sb", n=2, synth={"intrinsics": [40.0, 40.0, 15.5, 11.5],
                                                   "sensor": {"depth_noise": "loud"}})
    with pytest.raises(DynslamError, match="sensor.depth_noise' must be a number"):
        open_sequence(str(bad))


def test_synth_name_renders_once_into_cache(tmp_path: Path, monkeypatch):
    import types

    calls = []

    def render_preset(preset, out_dir, cfg, frames=None, progress=True):
        calls.append((preset, Path(out_dir), frames))
        make_folder(Path(out_dir), n=frames, w=cfg.width, h=cfg.height,
                    synth={"intrinsics": [20.0, 20.0, 8.0, 6.0], "preset": preset})

    fake = types.ModuleType("dynslam_cli.synth.render")
    fake.render_preset = render_preset
    monkeypatch.setitem(sys.modules, "dynslam_cli.synth.render", fake)
    cfg = load_config("synth", "walker", overrides=[f"data.root={tmp_path}", "synth.width=16",
                                                   "synth.height=12", "synth.frames=4", "synth.seed=3"])
    seq = open_sequence("synth/walker", cfg)
    assert seq.path == tmp_path / "synth" / "walker_16x12_4f_s3"
    assert len(seq) == 4 and seq.dataset == "synth" and seq.spec == "synth/walker"
    assert len(calls) == 1 and calls[0][0] == "walker" and calls[0][2] == 4
    assert calls[0][1] != seq.path  # rendered into a temporary folder, then renamed
    open_sequence("synth/walker", cfg)
    assert len(calls) == 1  # cached

    def broken(preset, out_dir, cfg, frames=None, progress=True):
        (Path(out_dir) / "rgb").mkdir()
        raise RuntimeError("renderer crashed")

    fake.render_preset = broken
    cfg2 = load_config("synth", "other", overrides=[f"data.root={tmp_path}", "synth.frames=2"])
    with pytest.raises(RuntimeError):
        open_sequence("synth/other", cfg2)
    assert sorted(p.name for p in (tmp_path / "synth").iterdir()) == ["walker_16x12_4f_s3"]


def test_synth_sensor_settings_name_their_own_scene(tmp_path: Path, monkeypatch):
    import json
    import types

    calls = []

    def render_preset(preset, out_dir, cfg, frames=None, progress=True):
        calls.append(cfg.depth_noise)
        make_folder(Path(out_dir), n=frames, w=cfg.width, h=cfg.height,
                    synth={"intrinsics": [20.0, 20.0, 8.0, 6.0], "preset": preset,
                           "sensor": {"depth_noise": cfg.depth_noise, "depth_holes": cfg.depth_holes,
                                      "rgb_noise": cfg.rgb_noise}})

    fake = types.ModuleType("dynslam_cli.synth.render")
    fake.render_preset = render_preset
    monkeypatch.setitem(sys.modules, "dynslam_cli.synth.render", fake)
    base = [f"data.root={tmp_path}", "synth.width=16", "synth.height=12", "synth.frames=2"]
    plain = open_sequence("synth/static", load_config("synth", "static", overrides=base))
    quiet = open_sequence("synth/static", load_config("synth", "static", overrides=base + [
        "synth.depth_noise=0", "synth.rgb_noise=0.5"]))
    assert plain.path.name == "static_16x12_2f_s0" and quiet.path.name == "static_16x12_2f_s0_dn0_cn0.5"
    assert calls == [0.002, 0.0]  # a scene of its own, not the cached noisy one
    open_sequence("synth/static", load_config("synth", "static", overrides=base + ["synth.depth_noise=0.0",
                                                                                   "synth.rgb_noise=0.5"]))
    assert len(calls) == 2  # the same settings find their scene again
    # a cached folder that says it was rendered otherwise (an older version's, edited by hand) is refused
    meta = json.loads((plain.path / "synth.json").read_text())
    meta["sensor"]["depth_holes"] = 0.2
    (plain.path / "synth.json").write_text(json.dumps(meta))
    with pytest.raises(DynslamError, match=r"static_16x12_2f_s0 holds synth/static rendered with depth_holes 0.2, "
                                           r"not synth.depth_holes 0.01"):
        open_sequence("synth/static", load_config("synth", "static", overrides=base))
    assert len(calls) == 2  # and left as it was


def test_named_sequences_under_root(tmp_path: Path, monkeypatch):
    make_folder(tmp_path / "rgbd_dataset_freiburg3_walking_xyz", n=2)
    make_folder(tmp_path / "bonn" / "rgbd_bonn_crowd", n=3)
    seq = open_sequence("tum/fr3_walking_xyz", load_config("tum", "fr3_walking_xyz", overrides=[f"data.root={tmp_path}"]))
    assert seq.intrinsics.fx == pytest.approx(535.4) and len(seq) == 2 and seq.name == "fr3_walking_xyz"
    assert not seq.undistorted  # fr3: zero distortion
    monkeypatch.setenv("DYNSLAM_DATA", str(tmp_path))
    seq = open_sequence("bonn/crowd")  # config resolved from configs/bonn.yaml, root from env
    assert seq.path == tmp_path / "bonn" / "rgbd_bonn_crowd" and seq.intrinsics.fx == pytest.approx(542.822841)


def test_intrinsics_scaled():
    k = Intrinsics(500.0, 400.0, 319.5, 239.5, 640, 480)
    assert np.array_equal(k.K, [[500, 0, 319.5], [0, 400, 239.5], [0, 0, 1]])
    h = k.scaled(0.5)
    assert (h.width, h.height) == (320, 240) and h.fx == 250.0 and h.fy == 200.0
    assert (h.cx, h.cy) == (159.5, 119.5)  # the image centre stays the centre
    assert k.scaled(2.0).scaled(0.5) == k


def test_data_package_import_is_light():
    code = ("import sys, dynslam_cli.data, dynslam_cli.data.names, dynslam_cli.commands.data; "
            "heavy = [m for m in ('cv2', 'numpy', 'torch') if m in sys.modules]; print(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    from dynslam_cli import data

    assert data.open_sequence is open_sequence
