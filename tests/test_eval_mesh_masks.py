"""Mesh accuracy/completion on planes with known offsets; frustum culling; Bonn frame; mask IoU."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from dynslam_cli.errors import DynslamError
from dynslam_cli.eval.masks import compute_mask_metrics, evaluate_run_masks
from dynslam_cli.eval.mesh import (bonn_camera_in_reference, compute_mesh_metrics, evaluate_run_mesh,
                                   frustum_mask, T_M, T_ROS)


def plane(x0, x1, y0, y1, z, transform=None, n=8):
    xs, ys = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    v = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], 1)
    f = []
    for i in range(n - 1):
        for j in range(n - 1):
            a = i * n + j
            f += [[a, a + 1, a + n], [a + 1, a + n + 1, a + n]]
    m = trimesh.Trimesh(v, np.array(f), process=False)
    if transform is not None:
        m.apply_transform(transform)
    return m


def test_plane_shifted_by_one_cm(tmp_path):
    plane(0, 1, 0, 1, 0.0).export(tmp_path / "ref.ply")
    plane(0, 1, 0, 1, 0.01).export(tmp_path / "est.ply")
    r = compute_mesh_metrics(tmp_path / "est.ply", tmp_path / "ref.ply", samples=100000, threshold=0.05)
    assert r.accuracy_m == pytest.approx(0.01, abs=1.5e-3)
    assert r.completion_m == pytest.approx(0.01, abs=1.5e-3)
    assert r.completion_ratio == pytest.approx(1.0)
    r2 = compute_mesh_metrics(tmp_path / "est.ply", tmp_path / "ref.ply", samples=100000, threshold=0.005)
    assert r2.completion_ratio == pytest.approx(0.0)
    # half the reference missing from the estimate: completion grows, accuracy does not
    plane(0, 1, 0, 0.5, 0.01).export(tmp_path / "half.ply")
    r3 = compute_mesh_metrics(tmp_path / "half.ply", tmp_path / "ref.ply", samples=50000)
    assert r3.accuracy_m == pytest.approx(0.01, abs=2e-3)
    assert r3.completion_m > 0.1 and 0.45 < r3.completion_ratio < 0.6
    # a transform applied to the reference: shifting it by the same 1 cm gives ~0
    t = np.eye(4)
    t[2, 3] = 0.01
    r4 = compute_mesh_metrics(tmp_path / "est.ply", tmp_path / "ref.ply", ref_to_est=t, samples=50000)
    assert r4.accuracy_m < 4e-3


def test_frustum_mask():
    pts = np.array([[0, 0, 2.0], [0, 0, -2.0], [5, 0, 2.0], [0, 0, 9.0], [0.3, 0.2, 1.0]])
    keep = frustum_mask(pts, [np.eye(4)], [100, 100, 32, 24], 64, 48, max_depth=5.0)
    assert keep.tolist() == [True, False, False, False, True]
    pose = np.eye(4)
    pose[0, 3] = 5.0  # a second camera 5 m to the right sees the third point
    assert frustum_mask(pts, [np.eye(4), pose], [100, 100, 32, 24], 64, 48, 5.0).tolist() == [True, False, True, False, True]


def write_tum(path: Path, stamps, poses):
    lines = []
    for t, p in zip(stamps, poses, strict=False):
        q = Rotation.from_matrix(p[:3, :3]).as_quat()
        lines.append(" ".join(f"{v:.9f}" for v in [t, *p[:3, 3], *q]))
    path.write_text("\n".join(lines) + "\n")


def synth_run(tmp_path: Path, est_world: np.ndarray):
    """A synthetic scene (a 2x2 m wall at z=2, camera at the origin looking at it) and a run whose
    world frame is ``est_world`` · GT world, with a mesh of the visible part shifted 1 cm."""
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "synth.json").write_text(json.dumps({"intrinsics": [100, 100, 32, 24], "size": [64, 48]}))
    plane(-1, 1, -1, 1, 2.0, n=20).export(scene / "static_mesh.ply")
    stamps = [0.0, 0.1, 0.2]
    gt = []
    for x in (0.0, 0.02, 0.04):
        p = np.eye(4)
        p[0, 3] = x
        gt.append(p)
    write_tum(scene / "groundtruth.txt", stamps, gt)
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "traj_est.txt", stamps, [est_world @ p for p in gt])
    plane(-0.6, 0.65, -0.45, 0.45, 2.01, transform=est_world, n=12).export(run / "mesh.ply")
    (run / "run.json").write_text(json.dumps({"status": "completed", "sequence": {
        "dataset": "synth", "name": "scene", "path": str(scene), "groundtruth": str(scene / "groundtruth.txt")}}))
    (run / "config.yaml").write_text("eval:\n  completion_threshold: 0.05\n")
    return run


@pytest.mark.parametrize("moved", [False, True])
def test_run_mesh_synthetic_with_culling(tmp_path, moved, monkeypatch):
    monkeypatch.setattr("dynslam_cli.eval.mesh.MESH_SAMPLES", 100000)  # half the points: faster, the same figures
    est_world = np.eye(4)
    if moved:  # the run's world is not the GT world: the reference must follow the first camera
        est_world[:3, :3] = Rotation.from_rotvec([0.2, -0.5, 0.3]).as_matrix()
        est_world[:3, 3] = [1.0, 2.0, -0.5]
    run = synth_run(tmp_path, est_world)
    culled = evaluate_run_mesh(run)
    assert culled.culled and culled.samples == 100000
    assert culled.accuracy_m == pytest.approx(0.01, abs=2e-3)
    assert culled.completion_m < 0.03 and culled.completion_ratio > 0.9
    full = evaluate_run_mesh(run, cull=False)
    assert full.completion_m > 0.15 and full.completion_ratio < 0.4  # most of the wall was never seen
    saved = json.loads((run / "mesh_metrics.json").read_text())
    assert saved["culled"] is False and saved["completion_m"] == pytest.approx(full.completion_m)


def test_bonn_reference_frame(tmp_path):
    c_id = bonn_camera_in_reference(np.eye(4))
    r = c_id[:3, :3]
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-9) and np.linalg.det(r) == pytest.approx(1.0)
    # T_ros · I · T_ros = I, so C0 of an identity GT pose is T_m with its block projected onto SO(3):
    # the polar factor, i.e. r^T · M is symmetric positive definite
    assert np.allclose(T_ROS @ T_ROS, np.eye(4)) and np.allclose(c_id[:3, 3], T_M[:3, 3])
    sym = r.T @ T_M[:3, :3]
    assert np.allclose(sym, sym.T, atol=1e-9) and np.all(np.linalg.eigvalsh((sym + sym.T) / 2) > 0)
    # a Bonn run: the reference cloud given in the laser frame is brought into the run's frame
    t_gt = np.eye(4)
    t_gt[:3, :3] = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    t_gt[:3, 3] = [0.5, -1.5, 1.4]
    c0 = bonn_camera_in_reference(t_gt)
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "traj_est.txt", [0.0, 0.1], [np.eye(4), np.eye(4)])
    write_tum(tmp_path / "gt.txt", [0.0, 0.1], [t_gt, t_gt])
    wall = plane(-1, 1, -1, 1, 2.0, n=10)
    wall.export(run / "mesh.ply")
    cloud = trimesh.sample.sample_surface(wall, 30000, seed=1)[0] @ c0[:3, :3].T + c0[:3, 3]
    trimesh.PointCloud(cloud).export(tmp_path / "laser.ply")
    (run / "run.json").write_text(json.dumps({"status": "completed", "sequence": {
        "dataset": "bonn", "name": "crowd", "groundtruth": str(tmp_path / "gt.txt")}}))
    (run / "config.yaml").write_text("eval:\n  completion_threshold: 0.05\n")
    res = evaluate_run_mesh(run, ref=tmp_path / "laser.ply", cull=False)
    assert res.accuracy_m < 0.01 and res.completion_ratio > 0.99
    with pytest.raises(DynslamError, match="--ref"):
        evaluate_run_mesh(run)


def _png(path: Path, mask: np.ndarray):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), mask.astype(np.uint8) * 255)


def test_mask_metrics_known_values(tmp_path):
    pred, gt = np.zeros((3, 20, 20), bool), np.zeros((3, 20, 20), bool)
    pred[0, 0:10, 0:10] = True
    gt[0, 5:15, 0:10] = True  # inter 50, union 150
    pred[2, 0, 0:10] = True  # a false alarm on a frame without movers
    for i, ts in enumerate(["1.000000", "1.033333", "1.066667"]):
        _png(tmp_path / "run" / "masks" / f"{ts}.png", pred[i])
        _png(tmp_path / "scene" / "dynamic" / f"{ts}.png", gt[i])
    r = compute_mask_metrics(tmp_path / "run" / "masks", tmp_path / "scene" / "dynamic")
    assert r.frames == 3 and r.frames_moving == 1
    assert r.mean_iou_moving == pytest.approx(1 / 3)
    assert r.mean_precision_moving == pytest.approx(0.5) and r.mean_recall_moving == pytest.approx(0.5)
    assert r.mean_iou_all == pytest.approx((1 / 3 + 1 + 0) / 3)
    assert r.mean_precision_all == pytest.approx(0.25)  # frames 0 and 2 have predictions
    assert r.pooled_iou == pytest.approx(50 / (150 + 10))
    (tmp_path / "run" / "run.json").write_text(json.dumps({"status": "completed", "sequence": {
        "dataset": "synth", "path": str(tmp_path / "scene")}}))
    evaluate_run_masks(tmp_path / "run")
    saved = json.loads((tmp_path / "run" / "mask_metrics.json").read_text())
    assert saved["mean_iou_moving"] == pytest.approx(1 / 3) and len(saved["per_frame"]) == 3
    # size mismatch is a one-line error naming both files
    _png(tmp_path / "run" / "masks" / "1.000000.png", np.zeros((10, 10), bool))
    with pytest.raises(DynslamError, match="10x10"):
        compute_mask_metrics(tmp_path / "run" / "masks", tmp_path / "scene" / "dynamic")


def test_cli_eval_mesh_and_masks_errors(tmp_path):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    run = synth_run(tmp_path, np.eye(4))
    res = CliRunner().invoke(app, ["eval-mesh", str(run), "--no-cull"])
    assert res.exit_code == 0, res.output
    assert "accuracy" in res.output and (run / "mesh_metrics.json").is_file()
    res = CliRunner().invoke(app, ["eval-masks", str(run)])
    assert res.exit_code == 2 and "error:" in res.output
    (run / "mesh.ply").write_bytes(b"not a ply")
    res = CliRunner().invoke(app, ["eval-mesh", str(run)])
    assert res.exit_code == 2 and "mesh" in res.output


def test_cli_eval_mesh_and_masks_refuse_incomplete_runs(tmp_path):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    run = synth_run(tmp_path, np.eye(4))
    _png(run / "masks" / "0.000000.png", np.zeros((48, 64), bool))
    _png(tmp_path / "scene" / "dynamic" / "0.000000.png", np.zeros((48, 64), bool))
    meta = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**meta, "status": "interrupted"}))
    for cmd, out in (("eval-mesh", "mesh_metrics.json"), ("eval-masks", "mask_metrics.json")):
        res = CliRunner().invoke(app, [cmd, str(run), "--no-cull"] if cmd == "eval-mesh" else [cmd, str(run)])
        assert res.exit_code == 2 and not (run / out).exists()
        assert res.output.strip() == (f"error: run {run} is not completed (run.json status: interrupted); "
                                      "pass --include-incomplete to use it anyway")
        res = CliRunner().invoke(app, [*([cmd, str(run), "--no-cull"] if cmd == "eval-mesh" else [cmd, str(run)]),
                                       "--include-incomplete"])
        assert res.exit_code == 0, res.output
        assert (run / out).is_file()
    # several folders: the incomplete one is skipped with a warning, the others are evaluated
    other = tmp_path / "other"
    other.mkdir()
    (other / "run.json").write_text(json.dumps({"status": "running"}))
    (run / "run.json").write_text(json.dumps(meta))
    res = CliRunner().invoke(app, ["eval-masks", str(run), str(other)])
    assert res.exit_code == 0, res.output
    assert res.stderr.strip() == (f"warning: skipped: run {other} is not completed (run.json status: running); "
                                  "pass --include-incomplete to use it anyway")
    assert not (other / "mask_metrics.json").exists()
