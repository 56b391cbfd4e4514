"""`dynslam view`: a Rerun recording of run folders, read back with rerun's RRD reader."""

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from dynslam_cli.cli import app
from dynslam_cli.data.tum import read_trajectory
from dynslam_cli.errors import DynslamError
from dynslam_cli.slam.toyscene import write_sequence

rr = pytest.importorskip("rerun", reason='rerun-sdk not installed (pip install "dynslam_cli[view]")')
from rerun.chunk import RrdReader  # noqa: E402

from dynslam_cli.view.recording import write_recording  # noqa: E402

N, W, H = 7, 40, 30
# the estimate lives in another world frame than the ground truth: est = A @ gt
A = np.eye(4)
A[:3, :3] = Rotation.from_euler("zyx", [30, -10, 5], degrees=True).as_matrix()
A[:3, 3] = [0.5, -0.2, 0.1]


def _tum_lines(stamps, poses):
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    return "".join(f"{s} {T[0, 3]:.9f} {T[1, 3]:.9f} {T[2, 3]:.9f} {a[0]:.9f} {a[1]:.9f} {a[2]:.9f} {a[3]:.9f}\n"
                   for s, T, a in zip(stamps, poses, q, strict=True))


def _stamps(clip):
    return [ln.split()[0] for ln in (clip / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]


def make_run(run, clip, poses_c2w, stamps, extras=True):
    """A run folder written by hand: run.json, traj_est.txt and (with ``extras``) masks, rendered
    depths, classifier updates and a mesh, in the formats `dynslam run` writes them."""
    run.mkdir(parents=True)
    meta = {"status": "completed", "mode": "dynamic",
            "sequence": {"spec": str(clip), "dataset": "synth", "name": clip.name, "path": str(clip),
                         "groundtruth": str(clip / "groundtruth.txt")}}
    (run / "run.json").write_text(json.dumps(meta))
    (run / "traj_est.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + _tum_lines(stamps, poses_c2w))
    if not extras:
        return run
    import trimesh

    (run / "masks").mkdir()
    (run / "renders").mkdir()
    for i in (0, 2, 3, 4):  # motion masks where saved (frame 3 is not an image frame at --every 2)
        m = np.zeros((H, W), np.uint8)
        m[5:15, 10 + i:20 + i] = 255
        cv2.imwrite(str(run / "masks" / f"{stamps[i]}.png"), m)
    for i in (2, 4):  # rendered at half resolution, as the check does
        cv2.imwrite(str(run / "renders" / f"{stamps[i]}_depth.png"), np.full((H // 2, W // 2), 5000 + i, np.uint16))
    ups = [{"frame": 2, "timestamp": stamps[2], "loss_after": 0.5}, {"frame": 5, "loss_after": 0.25},
           {"frame": 4, "timestamp": stamps[4], "loss_after": 0.4}]
    (run / "classifier_updates.jsonl").write_text("".join(json.dumps(u) + "\n" for u in ups))
    trimesh.creation.box(extents=[1, 2, 3]).export(run / "mesh.ply")
    return run


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("view")
    clip = write_sequence(root / "toybox", n=N, width=W, height=H, step=0.05)
    stamps = _stamps(clip)
    _, gt = read_trajectory(clip / "groundtruth.txt")
    run = make_run(root / "runs" / "toy" / "dynamic", clip, A @ gt, stamps)
    return clip, run, stamps, A @ gt


def read_rrd(path):
    ents = {}
    for c in RrdReader(path).stream():
        ents.setdefault(c.entity_path, []).append(c.to_record_batch().to_pydict())
    return ents


def column(ents, path, comp):
    """``(frames, values)`` of the rows of ``path`` holding ``comp``, by frame (static rows: frame None)."""
    rows = []
    for b in ents.get(path, []):
        if comp in b:
            frames = b.get("frame", [None] * len(b[comp]))
            rows += [(f, v) for f, v in zip(frames, b[comp], strict=True) if v is not None]
    rows.sort(key=lambda r: -1 if r[0] is None else r[0])
    return [r[0] for r in rows], [r[1] for r in rows]


def test_recording_holds_every_part(scene, tmp_path):
    clip, run, stamps, est = scene
    out = tmp_path / "rec.rrd"
    res = write_recording([run], out=out, every=2)
    assert res.out == out and out.is_file() and res.size_bytes == out.stat().st_size and not res.spawned
    v = res.runs[0]
    assert (v.prefix, v.frames, v.every, v.image_frames) == ("dynamic", N, 2, 4)
    assert (v.masks, v.renders, v.updates, v.mesh_vertices, v.alignment) == (3, 2, 3, 8, "se3")
    assert v.groundtruth_poses == N and v.ate_rmse_m < 1e-6
    ents = read_rrd(out)
    P = "/dynamic"
    for part in ("trajectory/estimate", "trajectory/groundtruth", "camera", "camera/rgb", "camera/depth",
                 "camera/mask", "camera/render_depth", "mesh", "classifier/updates", "ate/error"):
        assert f"{P}/{part}" in ents, part
    # frusta: the pinhole once, the estimated pose at every frame
    frames, trans = column(ents, f"{P}/camera", "Transform3D:translation")
    assert frames == list(range(N))
    assert np.allclose(np.array(trans, dtype=float).reshape(N, 3), est[:, :3, 3], atol=1e-6)
    assert column(ents, f"{P}/camera", "Pinhole:resolution")[0] == [None]
    # the ground truth drawn in the estimate's frame: undoing A puts it onto the estimate
    _, strips = column(ents, f"{P}/trajectory/groundtruth", "LineStrips3D:strips")
    assert np.allclose(np.array(strips[0][0], dtype=float), est[:, :3, 3], atol=1e-5)
    # images every 2nd frame; masks and renders where saved among those, at the camera size
    assert column(ents, f"{P}/camera/rgb", "EncodedImage:blob")[0] == [0, 2, 4, 6]
    frames, depth = column(ents, f"{P}/camera/depth", "DepthImage:buffer")
    assert frames == [0, 2, 4, 6]
    raw = cv2.imread(str(clip / "depth" / f"{stamps[2]}.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(np.frombuffer(bytes(depth[1][0]), np.uint16).reshape(H, W), raw)
    _, jpg = column(ents, f"{P}/camera/rgb", "EncodedImage:blob")
    rgb = cv2.imread(str(clip / "rgb" / f"{stamps[4]}.png"))
    dec = cv2.imdecode(np.frombuffer(bytes(jpg[2][0]), np.uint8), cv2.IMREAD_COLOR)
    assert dec.shape == rgb.shape  # JPEG of a tiny checkerboard: the channel means and patterns hold
    assert np.abs(dec.mean(axis=(0, 1)) - rgb.mean(axis=(0, 1))).max() < 4
    assert min(np.corrcoef(dec[..., c].ravel(), rgb[..., c].ravel())[0, 1] for c in range(3)) > 0.8
    frames, masks = column(ents, f"{P}/camera/mask", "SegmentationImage:buffer")
    assert frames == [0, 2, 4]
    m = np.frombuffer(bytes(masks[1][0]), np.uint8).reshape(H, W)
    assert m.sum() == 100 and m[5:15, 12:22].all()
    frames, rendered = column(ents, f"{P}/camera/render_depth", "DepthImage:buffer")
    assert frames == [2, 4] and set(np.frombuffer(bytes(rendered[1][0]), np.uint16)) == {5004}
    # classifier updates: the count so far, placed by timestamp, else by frame index
    frames, counts = column(ents, f"{P}/classifier/updates", "Scalars:scalars")
    assert frames == [2, 4, 5] and [c[0] for c in counts] == [1, 2, 3]
    assert len(column(ents, f"{P}/ate/error", "Scalars:scalars")[0]) == N
    _, verts = column(ents, f"{P}/mesh", "Mesh3D:vertex_positions")
    assert np.allclose(np.abs(np.array(verts[0], dtype=float)).max(axis=0), [0.5, 1, 1.5])


def test_two_runs_one_recording(scene, tmp_path):
    clip, _, stamps, est = scene
    a = make_run(tmp_path / "runs" / "a" / "dynamic", clip, est, stamps)
    b = make_run(tmp_path / "runs" / "b" / "dynamic", clip, est[:4], stamps[:4], extras=False)
    res = write_recording([a, b])
    assert res.out == tmp_path / "runs" / "recording.rrd"  # the runs' common folder
    assert [v.prefix for v in res.runs] == ["a/dynamic", "b/dynamic"]
    assert [v.every for v in res.runs] == [1, 1] and [v.image_frames for v in res.runs] == [N, 4]
    assert res.runs[1].notes == ["no mesh.ply"]
    ents = read_rrd(res.out)
    assert column(ents, "/a/dynamic/camera/rgb", "EncodedImage:blob")[0] == list(range(N))
    assert column(ents, "/b/dynamic/camera/rgb", "EncodedImage:blob")[0] == [0, 1, 2, 3]
    assert "/b/dynamic/mesh" not in ents and "/b/dynamic/classifier/updates" not in ents


def test_cli_writes_the_default_file_and_says_how_to_open_it(scene, tmp_path):
    _, run, _, _ = scene
    r = CliRunner().invoke(app, ["view", str(run), "--every", "3"])
    assert r.exit_code == 0, r.output
    assert (run / "recording.rrd").is_file() and f"rerun {run / 'recording.rrd'}" in r.output
    assert "dynamic: 7 frames, images of 3 (every 3)" in r.output
    (run / "recording.rrd").unlink()


def test_spawn_without_a_display_still_writes_the_file(scene, tmp_path, monkeypatch):
    _, run, _, _ = scene
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    res = write_recording([run], out=tmp_path / "s.rrd", spawn=True)
    assert not res.spawned and res.notes and res.notes[0].startswith("viewer not opened: no display")
    assert (tmp_path / "s.rrd").is_file()


def _fails(args, message):
    r = CliRunner().invoke(app, ["view", *map(str, args)])
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0], r.output


def test_user_errors_leave_the_recording_unchanged(scene, tmp_path, monkeypatch):
    clip, run, stamps, est = scene
    out = tmp_path / "keep.rrd"
    write_recording([run], out=out)
    before = out.read_bytes()
    _fails([tmp_path / "nope", "--out", out], "run folder not found")
    _fails([run, "--out", out, "--every", "0"], "--every must be >= 1")
    _fails([run, "--out", tmp_path / "rec.txt"], "must end in .rrd")
    _fails([run, run, "--out", out], "given twice")
    empty = tmp_path / "empty"
    empty.mkdir()
    _fails([empty, "--out", out], "traj_est.txt not found")
    bad = make_run(tmp_path / "bad", clip, est, stamps)
    (bad / "masks" / f"{stamps[2]}.png").write_bytes(b"not a png")
    _fails([bad, "--out", out, "--every", "2"], "corrupt motion mask")
    (bad / "masks" / f"{stamps[2]}.png").unlink()
    (bad / "classifier_updates.jsonl").write_text('{"frame": 1}\n[1, 2]\n')
    _fails([bad, "--out", out], "classifier_updates.jsonl")
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no temp files left
    monkeypatch.setitem(__import__("sys").modules, "rerun", None)
    _fails([run, "--out", out], 'pip install "dynslam_cli[view]"')
    with pytest.raises(DynslamError, match="not installed"):
        write_recording([run], out=out)
    assert out.read_bytes() == before


def test_real_bonn_frames(bonn_clip, tmp_path):
    """A run folder over the first frames of the real Bonn clip (trajectory: its ground truth)."""
    from dynslam_cli.config import load_config
    from dynslam_cli.data.tum import read_folder

    cfg = load_config("bonn", "crowd", overrides=["data.frames=5"])
    seq = read_folder(bonn_clip, cfg, dataset="bonn", name="crowd", spec=str(bonn_clip))
    poses = np.stack([p for p in seq.gt_poses if p is not None])
    assert len(poses) == 5, "the clip's first frames have ground truth"
    run = tmp_path / "bonn_run"
    run.mkdir()
    gt = seq.groundtruth_file
    (run / "run.json").write_text(json.dumps({"status": "completed", "sequence": {
        "spec": "bonn/crowd", "dataset": "bonn", "name": "crowd", "path": str(bonn_clip), "groundtruth": str(gt)}}))
    (run / "traj_est.txt").write_text(_tum_lines(seq.stamps, poses))
    res = write_recording([run], out=tmp_path / "bonn.rrd", every=2)
    v = res.runs[0]
    assert (v.frames, v.image_frames, v.groundtruth_poses > 0) == (5, 3, True), v.notes
    assert v.ate_rmse_m < 1e-3
    ents = read_rrd(tmp_path / "bonn.rrd")
    frames, depth = column(ents, "/bonn_run/camera/depth", "DepthImage:buffer")
    assert frames == [0, 2, 4]
    w, h = seq.intrinsics.width, seq.intrinsics.height
    d = np.frombuffer(bytes(depth[0][0]), np.uint16).reshape(h, w)
    assert np.allclose(d / 5000.0, seq.load_depth(0), atol=1e-3) and (d > 0).mean() > 0.3
    assert column(ents, "/bonn_run/camera/rgb", "EncodedImage:blob")[0] == [0, 2, 4]
