"""The synthetic scene renderer: folder layout, determinism, geometric consistency of the ground
truth, motion masks, the kidnap story, the CLI.  Tiny images and few frames keep it fast."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynslam_cli.config import Config  # noqa: F401  (import order: config before synth.config)
from dynslam_cli.errors import DynslamError
from dynslam_cli.synth.config import SynthConfig
from dynslam_cli.synth.render import PRESETS, render_preset

W, H = 64, 48


def cfg(**kw) -> SynthConfig:
    c = SynthConfig(width=W, height=H)
    for k, v in kw.items():
        setattr(c, k, v)
    return c


# ----------------------------------------------------------------------------- a tiny reader


def read_scene(d: Path) -> dict:
    """Read a scene folder independently of the library's reader."""
    meta = json.loads((d / "synth.json").read_text())

    def listing(name):
        rows = [ln.split() for ln in (d / name).read_text().splitlines() if ln and not ln.startswith("#")]
        return rows

    rgb_rows, depth_rows, gt_rows = listing("rgb.txt"), listing("depth.txt"), listing("groundtruth.txt")
    frames = []
    for (ts, rgb_name), (ts_d, depth_name), gt in zip(rgb_rows, depth_rows, gt_rows, strict=True):
        assert ts == ts_d == gt[0]
        rgb = cv2.imread(str(d / rgb_name), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(d / depth_name), cv2.IMREAD_UNCHANGED)
        inst = cv2.imread(str(d / "instances" / f"{ts}.png"), cv2.IMREAD_UNCHANGED)
        dyn = cv2.imread(str(d / "dynamic" / f"{ts}.png"), cv2.IMREAD_UNCHANGED)
        vals = np.array([float(v) for v in gt[1:]])
        frames.append(dict(ts=ts, rgb=rgb, depth_raw=depth, depth=depth.astype(np.float64) / meta["depth_scale"],
                           inst=inst, dyn=dyn, pose=pose_matrix(vals)))
    return dict(meta=meta, frames=frames, rows=(rgb_rows, depth_rows, gt_rows))


def pose_matrix(v: np.ndarray) -> np.ndarray:
    tx, ty, tz, qx, qy, qz, qw = v
    R = np.array([
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
    ])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, (tx, ty, tz)
    return T


def backproject(depth: np.ndarray, mask: np.ndarray, intr, T: np.ndarray) -> np.ndarray:
    fx, fy, cx, cy = intr
    v, u = np.nonzero(mask)
    z = depth[v, u]
    pc = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)
    return pc @ T[:3, :3].T + T[:3, 3]


def mesh_distance(points: np.ndarray, mesh) -> np.ndarray:
    """Exact distance from points to the nearest face whose interior they project into."""
    tri = np.asarray(mesh.triangles)
    n = np.asarray(mesh.face_normals)
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d00, d01, d11 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    den = d00 * d11 - d01 * d01
    out = np.empty(len(points))
    for s in range(0, len(points), 256):
        w = points[s:s + 256, None, :] - a[None]
        dist = (w * n[None]).sum(-1)
        q = w - dist[..., None] * n[None]
        d20, d21 = (q * e1[None]).sum(-1), (q * e2[None]).sum(-1)
        bv = (d11 * d20 - d01 * d21) / den
        bw = (d00 * d21 - d01 * d20) / den
        inside = (bv >= -1e-3) & (bw >= -1e-3) & (bv + bw <= 1 + 1e-3)
        out[s:s + 256] = np.where(inside, np.abs(dist), np.inf).min(axis=1)
    return out


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    made = {}

    def get(preset: str, frames: int = 12, seed: int = 0, tag: str = "", **kw) -> Path:
        key = (preset, frames, seed, tag)
        if key not in made:
            out = root / f"{preset}_{frames}_{seed}{tag}"
            render_preset(preset, out, cfg(seed=seed, **kw), frames=frames, progress=False)
            made[key] = out
        return made[key]

    return get


# ----------------------------------------------------------------------------- layout


def test_presets_listed():
    assert set(PRESETS) == {"static", "walker", "crowd", "kidnap", "balloon", "tracking"}


def test_unknown_preset_lists_presets(tmp_path):
    with pytest.raises(DynslamError, match=r"unknown synthetic preset 'nope'; presets: static, walker"):
        render_preset("nope", tmp_path / "x", cfg(), frames=2, progress=False)
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("preset", PRESETS)
def test_layout_complete_and_readable(scenes, preset):
    d = scenes(preset, frames=6)
    s = read_scene(d)
    meta = s["meta"]
    assert meta["preset"] == preset and meta["seed"] == 0 and meta["frames"] == 6
    assert meta["size"] == [W, H] and meta["depth_scale"] == 5000 and meta["fps"] == 30.0
    fx, fy, cx, cy = meta["intrinsics"]
    assert fx == pytest.approx(525 * W / 640) and fy == pytest.approx(525 * H / 480)
    assert (cx, cy) == ((W - 1) / 2, (H - 1) / 2)
    assert len(s["frames"]) == 6
    for i, (r, dr, g) in enumerate(zip(*s["rows"], strict=True)):
        assert r[0] == f"{i / 30:.6f}" and re.fullmatch(r"\d+\.\d{6}", r[0])
        assert r[1] == f"rgb/{r[0]}.png" and dr[1] == f"depth/{r[0]}.png" and len(g) == 8
        assert np.linalg.norm([float(v) for v in g[4:]]) == pytest.approx(1.0, abs=1e-6)
    for f in s["frames"]:
        assert f["rgb"].shape == (H, W, 3) and f["rgb"].dtype == np.uint8
        assert f["depth_raw"].shape == (H, W) and f["depth_raw"].dtype == np.uint16
        assert f["inst"].shape == (H, W) and f["inst"].dtype == np.uint16
        assert f["dyn"].shape == (H, W) and f["dyn"].dtype == np.uint8
        assert set(np.unique(f["dyn"])) <= {0, 255}
        valid = f["depth"] > 0
        assert valid.mean() > 0.8 and f["depth"][valid].max() < 8.0
        assert f["rgb"].std() > 10  # textured, not flat
        R = f["pose"][:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-6)
        assert 1.0 < f["pose"][2, 3] < 1.9  # camera height (z up)
    ids = [inst["id"] for inst in meta["instances"]]
    assert len(ids) == len(set(ids)) and min(ids) >= 1
    for inst in meta["instances"]:
        assert inst["kind"] in ("static", "mover")
        lo, hi = np.array(inst["aabb_first"]), np.array(inst["aabb_last"])
        assert lo.shape == (2, 3) and np.all(lo[0] <= lo[1]) and np.all(hi[0] <= hi[1])
    seen = set(np.unique(np.concatenate([f["inst"].ravel() for f in s["frames"]]))) - {0}
    assert seen <= set(ids)
    movers = [i for i in meta["instances"] if i["kind"] == "mover"]
    assert (len(movers) == 0) == (preset == "static")
    import trimesh

    mesh = trimesh.load(d / "static_mesh.ply", force="mesh")
    assert (d / "static_mesh.ply").read_bytes().startswith(b"ply\nformat binary")
    assert len(mesh.faces) > 100
    assert np.allclose(mesh.bounds, [[-2.5, -2.0, 0.0], [2.5, 2.0, 2.7]], atol=1e-5)
    assert not list(d.parent.glob(f".{d.name}.*"))  # no temp folders left behind


# ----------------------------------------------------------------------------- determinism


def _all_bytes(d: Path) -> dict:
    return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_deterministic_per_seed(tmp_path):
    a = render_preset("walker", tmp_path / "a", cfg(seed=3), frames=5, progress=False)
    b = render_preset("walker", tmp_path / "b", cfg(seed=3), frames=5, progress=False)
    c = render_preset("walker", tmp_path / "c", cfg(seed=4), frames=5, progress=False)
    fa, fb, fc = _all_bytes(a.out_dir), _all_bytes(b.out_dir), _all_bytes(c.out_dir)
    assert fa.keys() == fb.keys() and all(fa[k] == fb[k] for k in fa)
    differ = [k for k in fa if k.startswith(("rgb/", "depth/")) and fa[k] != fc.get(k)]
    assert len(differ) == 10
    assert fa["groundtruth.txt"] != fc["groundtruth.txt"]
    assert fa["static_mesh.ply"] != fc["static_mesh.ply"]


# ----------------------------------------------------------------------------- geometry


@pytest.mark.parametrize("preset", ["static", "walker", "kidnap"])
def test_static_depth_lies_on_static_mesh(scenes, preset):
    """Noise-free depth of static pixels, back-projected with the GT pose, lies on the mesh."""
    import trimesh

    d = scenes(preset, frames=24, tag="clean", depth_noise=0.0, depth_holes=0.0, rgb_noise=0.0)
    s = read_scene(d)
    mesh = trimesh.load(d / "static_mesh.ply", force="mesh")
    static_ids = {0} | {i["id"] for i in s["meta"]["instances"] if i["kind"] == "static"}
    for f in s["frames"][::5]:
        mask = (f["depth"] > 0) & np.isin(f["inst"], list(static_ids)) & (f["dyn"] == 0)
        assert mask.mean() > 0.3
        pts = backproject(f["depth"], mask, s["meta"]["intrinsics"], f["pose"])
        dist = mesh_distance(pts, mesh)
        # Quantisation is 0.2 mm in depth; allow for the longer ray at the image border.
        assert np.quantile(dist, 0.999) < 1.5e-3, (preset, f["ts"], np.sort(dist)[-5:])
        assert np.median(dist) < 3e-4
    if preset != "static":  # mover pixels do not lie on the static mesh
        mover_ids = [i["id"] for i in s["meta"]["instances"] if i["kind"] == "mover"]
        f = max(s["frames"], key=lambda fr: np.isin(fr["inst"], mover_ids).sum())
        mask = (f["depth"] > 0) & np.isin(f["inst"], mover_ids)
        assert mask.sum() > 20
        dist = mesh_distance(backproject(f["depth"], mask, s["meta"]["intrinsics"], f["pose"]), mesh)
        assert np.median(dist) > 0.05


def test_depth_noise_matches_model(scenes):
    """With sensor noise, residuals to the mesh scale like depth_noise * z^2."""
    import trimesh

    d = scenes("static", frames=12, tag="noisy", depth_noise=0.004, depth_holes=0.02)
    s = read_scene(d)
    mesh = trimesh.load(d / "static_mesh.ply", force="mesh")
    normed, holes = [], []
    for f in s["frames"][::4]:
        mask = f["depth"] > 0
        holes.append(1 - mask.mean())
        pts = backproject(f["depth"], mask, s["meta"]["intrinsics"], f["pose"])
        dist = mesh_distance(pts, mesh)
        z = f["depth"][mask]
        normed.append(dist / (0.004 * z * z))
    normed = np.concatenate(normed)
    normed = normed[np.isfinite(normed)]
    # |N(0,1)| measured along the surface normal: at most the full error, median below 0.6745.
    assert np.quantile(normed, 0.99) < 4.0
    assert 0.15 < np.median(normed) < 0.8
    assert 0.02 <= np.mean(holes) < 0.15  # random holes plus edge holes


# ----------------------------------------------------------------------------- motion


def _mover_ids(meta):
    return [i["id"] for i in meta["instances"] if i["kind"] == "mover"]


def test_static_preset_has_no_dynamic_pixels(scenes):
    s = read_scene(scenes("static", frames=6))
    assert all(f["dyn"].max() == 0 for f in s["frames"])


@pytest.mark.parametrize("preset", ["walker", "crowd", "balloon"])
def test_dynamic_mask_exactly_when_mover_in_view(scenes, preset):
    n = 45
    s = read_scene(scenes(preset, frames=n))
    ids = _mover_ids(s["meta"])
    visible = np.array([np.isin(f["inst"], ids).any() for f in s["frames"]])
    dynamic = np.array([f["dyn"].any() for f in s["frames"]])
    for f in s["frames"]:  # dynamic pixels are mover pixels
        assert np.all(np.isin(f["inst"][f["dyn"] > 0], ids))
    first = int(np.argmax(visible))
    assert visible.any() and 1 <= first <= 0.35 * n, first  # enters after the first frames
    assert visible[first:].mean() > 0.7  # then stays in view most of the time
    # These movers never stand still in view: dynamic pixels exactly in the frames showing one.
    assert np.array_equal(dynamic, visible)
    for f in s["frames"]:
        assert np.array_equal(f["dyn"] > 0, np.isin(f["inst"], ids))


def test_crowd_covers_large_parts_of_the_view(scenes):
    s = read_scene(scenes("crowd", frames=45))
    cover = [np.isin(f["inst"], _mover_ids(s["meta"])).mean() for f in s["frames"]]
    assert 0.12 < max(cover) <= 0.75


def test_tracking_keeps_the_walker_in_view(scenes):
    n = 20
    s = read_scene(scenes("tracking", frames=n))
    (wid,) = _mover_ids(s["meta"])
    vis = np.array([(f["inst"] == wid).mean() for f in s["frames"]])
    assert (vis > 0.03).all()
    dyn = np.array([f["dyn"].any() for f in s["frames"]])
    start = int(round(0.1 * n))
    assert not dyn[:start].any() and dyn[start + 2:].all()
    # The camera follows: it moves with the walker once the walker walks.
    c = np.array([f["pose"][:3, 3] for f in s["frames"]])
    assert np.linalg.norm(c[-1] - c[start]) > 0.15


def test_kidnap_box_is_carried_elsewhere(scenes):
    n = 40
    d = scenes("kidnap", frames=n)
    s = read_scene(d)
    inst = {i["name"]: i for i in s["meta"]["instances"]}
    box = inst["box"]
    assert box["kind"] == "mover" and inst["walker"]["kind"] == "mover"
    first, last = np.array(box["aabb_first"]), np.array(box["aabb_last"])
    assert np.linalg.norm(first.mean(0) - last.mean(0)) > 0.6
    assert abs(first[0, 2]) < 1e-6 and abs(last[0, 2]) < 1e-6  # on the floor at both ends
    assert np.allclose(first[1] - first[0], last[1] - last[0], atol=0.15)  # same box
    box_dyn = np.array([((f["inst"] == box["id"]) & (f["dyn"] > 0)).any() for f in s["frames"]])
    box_vis = np.array([(f["inst"] == box["id"]).any() for f in s["frames"]])
    assert box_vis[0] and not box_dyn[0]  # sits still at first
    assert box_dyn.any() and not box_dyn[-3:].any()  # moves, then stays
    import trimesh

    mesh = trimesh.load(d / "static_mesh.ply", force="mesh")
    for b in (first, last):  # the box is no part of the static mesh
        inside = np.all((mesh.triangles_center > b[0] + 0.01) & (mesh.triangles_center < b[1] - 0.01), axis=1)
        assert not inside.any()


# ----------------------------------------------------------------------------- folder safety


def test_out_dir_replaced_and_protected(tmp_path, monkeypatch):
    out = tmp_path / "scene"
    render_preset("static", out, cfg(), frames=2, progress=False)
    render_preset("static", out, cfg(), frames=3, progress=False)  # an earlier scene is replaced
    assert len(list((out / "rgb").iterdir())) == 3
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep")
    with pytest.raises(DynslamError, match="not empty"):
        render_preset("static", other, cfg(), frames=2, progress=False)
    assert (other / "notes.txt").read_text() == "keep"

    import dynslam_cli.synth.render as r

    calls = {"n": 0}
    real = r._write_frame

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("disk full")
        return real(*a, **k)

    monkeypatch.setattr(r, "_write_frame", failing)
    with pytest.raises(RuntimeError):
        render_preset("static", tmp_path / "half", cfg(), frames=4, progress=False)
    assert not (tmp_path / "half").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "scene"]
    calls["n"] = 0
    with pytest.raises(RuntimeError):  # the earlier complete scene survives a failed re-render
        render_preset("static", out, cfg(), frames=4, progress=False)
    assert len(list((out / "rgb").iterdir())) == 3


@pytest.mark.parametrize("bad", [dict(width=4), dict(depth_holes=1.5), dict(rgb_noise=-1.0)])
def test_bad_config_is_a_user_error(tmp_path, bad):
    with pytest.raises(DynslamError):
        render_preset("static", tmp_path / "x", cfg(**bad), frames=2, progress=False)


# ----------------------------------------------------------------------------- CLI


def test_cli_renders_and_reports(tmp_path):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    out = tmp_path / "cli"
    res = CliRunner().invoke(app, ["synth", "balloon", "--out", str(out), "--frames", "3", "--size", "40x30",
                                   "--seed", "5", "--set", "synth.rgb_noise=0", "-q"])
    assert res.exit_code == 0, res.output
    assert "synth balloon: 3 frames 40x30, seed 5" in res.output
    meta = json.loads((out / "synth.json").read_text())
    assert meta["size"] == [40, 30] and meta["seed"] == 5 and meta["frames"] == 3
    assert meta["sensor"]["rgb_noise"] == 0


@pytest.mark.parametrize("args, msg", [
    (["synth", "nope", "--out", "X"], "error: unknown synthetic preset 'nope'; presets: static, walker, crowd, "
                                      "kidnap, balloon, tracking"),
    (["synth", "static", "--out", "X", "--size", "big"], "error: --size 'big' must look like WIDTHxHEIGHT"),
    (["synth", "static", "--out", "X", "--set", "synth.bogus=1"], "error: unknown config key 'synth.bogus'"),
])
def test_cli_user_errors_exit_2_with_one_line(tmp_path, args, msg):
    from typer.testing import CliRunner

    from dynslam_cli.cli import app

    args = [str(tmp_path / "x") if a == "X" else a for a in args]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(msg), res.output
    assert not (tmp_path / "x").exists()
