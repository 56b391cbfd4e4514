"""Association (TUM associate.py semantics), trajectories, undistortion, Bonn transforms."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_data_helpers import data_cfg, make_folder

from dynslam_cli.data.tum import (
    associate,
    matrix_to_quat,
    poses_at,
    quat_to_matrix,
    read_trajectory,
)


def reference_associate(first, second, max_diff):
    """A literal transcription of associate.py's algorithm (dict-based, O(n·m))."""
    a = dict(enumerate(first))
    b = dict(enumerate(second))
    cands = sorted((abs(ta - tb), i, j) for i, ta in a.items() for j, tb in b.items() if abs(ta - tb) < max_diff)
    out = []
    for _, i, j in cands:
        if i in a and j in b:
            a.pop(i)
            b.pop(j)
            out.append((i, j))
    return sorted(out)


def test_associate_exact_and_one_to_one():
    assert associate([0.0, 1.0, 2.0], [0.0, 1.0, 2.0], 0.02) == [(0, 0), (1, 1), (2, 2)]
    # two rgb stamps compete for one depth stamp: the closer one wins, the other is dropped
    assert associate([0.000, 0.015], [0.010], 0.02) == [(1, 0)]
    # smallest difference first, even when it leaves an earlier rgb unmatched
    assert associate([0.0, 0.02], [0.011, 0.025], 0.02) == [(0, 0), (1, 1)]
    assert associate([0.0, 0.012], [0.011], 0.02) == [(1, 0)]


def test_associate_boundaries_and_order():
    assert associate([0.0], [0.02], 0.02) == []  # strictly less than max_diff
    assert associate([0.0], [0.0199], 0.02) == [(0, 0)]
    assert associate([], [1.0], 0.02) == [] and associate([1.0], [], 0.02) == []
    # unsorted second list: indices refer to the input order
    assert associate([0.0, 1.0], [1.001, 0.001], 0.02) == [(0, 1), (1, 0)]


def test_associate_matches_reference_on_random_stamps():
    rng = np.random.default_rng(0)
    for trial in range(30):
        a = np.sort(rng.uniform(0, 2, size=rng.integers(1, 40)))
        b = rng.uniform(0, 2, size=rng.integers(1, 40))
        md = float(rng.choice([0.005, 0.02, 0.1]))
        assert associate(a, b, md) == reference_associate(list(a), list(b), md), trial


def test_rgb_depth_association_in_reader(tmp_path: Path):
    # depth lags rgb by 7 ms; one rgb frame has no depth within 20 ms
    rgb = [0.0, 0.033, 0.066, 0.2]
    depth = [0.007, 0.040, 0.073, 0.5]
    d = make_folder(tmp_path / "s", rgb_ts=rgb, depth_ts=depth)
    seq = open_sequence_cfg(d)
    assert np.allclose(seq.timestamps, [0.0, 0.033, 0.066])
    assert [r.depth.name for r in seq.records] == ["0.007000.png", "0.040000.png", "0.073000.png"]
    assert seq.total_pairs == 3
    # a tighter max diff associates nothing: clear error with the value used
    from dynslam_cli.errors import DynslamError

    with pytest.raises(DynslamError, match=r"max_time_diff=0\.005 s"):
        open_sequence_cfg(d, max_time_diff=0.005)


def open_sequence_cfg(folder, **data):
    from dynslam_cli.data.open import open_sequence

    data.setdefault("intrinsics", [30, 30, 16, 12])
    return open_sequence(str(folder), data_cfg(**data))


def test_poses_at_rules():
    t = np.array([0.0, 0.03, 1.0])
    T = np.stack([np.eye(4)] * 3)
    T[:, 0, 3] = [0.0, 3.0, 10.0]
    out = poses_at([0.01, 0.03, 0.5, 0.99, 1.5], t, T, max_diff=0.02)
    assert out[0][0, 3] == pytest.approx(1.0)  # interpolated at 1/3
    assert out[1][0, 3] == 3.0  # exact sample
    assert out[2] is None  # nothing within 0.02
    assert out[3][0, 3] == 10.0  # gap 0.97 too wide to interpolate: nearest within 0.02
    assert out[4] is None  # after the end
    assert poses_at([0.0], np.zeros(0), np.zeros((0, 4, 4)), 0.02) == [None]


def test_quaternion_round_trip_and_trajectory_sorting(tmp_path: Path):
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = -q if q[3] < 0 else q
        R = quat_to_matrix(q)
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.allclose(matrix_to_quat(R), q)
    f = tmp_path / "gt.txt"
    f.write_text("# c\n2.0 1 2 3 0 0 0 2\n1.0 0 0 0 0 0 0 1\n")  # unnormalised quaternion, unsorted
    ts, poses = read_trajectory(f)
    assert list(ts) == [1.0, 2.0] and np.allclose(poses[1][:3, :3], np.eye(3)) and list(poses[1][:3, 3]) == [1, 2, 3]


# ------------------------------------------------------------------------------ undistortion
STRONG = [0.25, -0.9, 0.004, 0.003, 1.1]


def test_undistort_depth_is_nearest_no_mixing():
    from dynslam_cli.data.undistort import Undistorter

    h, w = 48, 64
    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    depth = np.full((h, w), 1.0, np.float32)
    depth[:, 30:] = 3.0  # a depth edge
    depth[10:14, 5:9] = 0.0  # a hole
    u = Undistorter(K, STRONG, w, h)
    out = u.depth(depth)
    assert out.dtype == np.float32
    assert set(np.unique(out)) <= {0.0, 1.0, 3.0}  # no value interpolated across the edge or hole
    assert (out != depth).any()  # it did move pixels
    assert out[h // 2, 10] == 1.0 and out[h // 2, 50] == 3.0
    # bilinear colour resampling does blend across the edge
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[:, 30:] = 200
    assert len(np.unique(u.rgb(rgb))) > 2
    ids = np.zeros((h, w), np.int32)
    ids[:, 30:] = 123456
    assert set(np.unique(u.nearest(ids))) <= {0, 123456}
    mask = ids > 0
    assert u.nearest(mask).dtype == np.bool_


def test_reader_undistorts_with_configured_distortion(tmp_path: Path):
    d = make_folder(tmp_path / "s", n=2, w=64, h=48)
    plain = open_sequence_cfg(d, intrinsics=[60.0, 60.0, 31.5, 23.5])[1]
    dist = open_sequence_cfg(d, intrinsics=[60.0, 60.0, 31.5, 23.5], distortion=STRONG)
    assert dist.undistorted
    f = dist[1]
    raw_values = set(np.unique(plain.depth))
    assert set(np.unique(f.depth)) <= raw_values | {0.0}
    assert not np.array_equal(f.depth, plain.depth) and not np.array_equal(f.rgb, plain.rgb)
    zero = open_sequence_cfg(d, intrinsics=[60.0, 60.0, 31.5, 23.5], distortion=[0, 0, 0, 0, 0])
    assert not zero.undistorted


# ------------------------------------------------------------------------------ Bonn
def test_bonn_reference_transform():
    from dynslam_cli.data import bonn

    Tm = bonn.rigid_T_m()
    R = Tm[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(Tm[:3, 3], bonn.T_M_RAW[:3, 3])
    # the projection is the nearest rotation: the raw block is that rotation times ~1.059
    scale = np.linalg.norm(bonn.T_M_RAW[:3, :3], axis=0)
    assert np.allclose(scale, 1.0593, atol=2e-3)
    assert np.allclose(bonn.T_M_RAW[:3, :3] / scale.mean(), R, atol=5e-3)
    # composition order T_ros · T_gt · T_ros · T_m, rigid result
    rng = np.random.default_rng(0)
    T_gt = np.eye(4)
    q = rng.normal(size=4)
    T_gt[:3, :3] = quat_to_matrix(q / np.linalg.norm(q))
    T_gt[:3, 3] = [0.3, -1.2, 1.5]
    out = bonn.gt_to_reference(T_gt)
    assert np.allclose(out, bonn.T_ROS @ T_gt @ bonn.T_ROS @ Tm)
    assert np.allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-9)
    raw = bonn.gt_to_reference(T_gt, project=False)
    assert np.allclose(raw, bonn.T_ROS @ T_gt @ bonn.T_ROS @ bonn.T_M_RAW)
    batch = bonn.gt_to_reference(np.stack([T_gt, np.eye(4)]))
    assert batch.shape == (2, 4, 4) and np.allclose(batch[0], out)


def test_bonn_depth_scale_is_the_calibrations():
    """configs/bonn.yaml reads depth in metres: PNG / 5000 times the scale of the dataset's own T_m."""
    from dynslam_cli.config import load_config
    from dynslam_cli.data import bonn

    f = bonn.DEPTH_SCALE_FACTOR
    assert f == pytest.approx(1.05929, abs=1e-5)
    assert np.allclose(np.linalg.svd(bonn.T_M_RAW[:3, :3])[1], f, atol=2e-4)  # isotropic: a scale, not a shear
    cfg = load_config("bonn", "crowd")
    assert cfg.data.depth_scale == pytest.approx(5000.0 / f, abs=0.01)
    assert cfg.data.max_depth == pytest.approx(3.0 * f, abs=1e-3)  # 3 m as read, in metres


def test_bonn_reference_cloud_lookup(tmp_path: Path):
    from dynslam_cli.data import bonn
    from dynslam_cli.errors import DynslamError

    with pytest.raises(DynslamError, match="dynslam download bonn/reference"):
        bonn.reference_cloud(tmp_path)
    p = tmp_path / bonn.REFERENCE_FOLDER / "rgbd_bonn_groundtruth_1mm_section.ply"
    p.parent.mkdir()
    p.write_bytes(b"ply\n")
    assert bonn.reference_cloud(tmp_path) == p
