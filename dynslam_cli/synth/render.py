"""Render a synthetic dynamic RGB-D sequence with full ground truth into a scene folder.

Layout (DEVELOPING.md, "Synthetic scene folder"): synth.json, rgb.txt, depth.txt,
groundtruth.txt, rgb/ depth/ instances/ dynamic/ <timestamp>.png, static_mesh.ply.  The folder
is rendered under a temporary name beside ``out_dir`` and renamed at the end, so a half-rendered
scene never looks complete.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.synth.scene import PRESETS, Scene, build_scene
from dynslam_cli.synth.sensor import DEPTH_SCALE, sense_depth, sense_rgb

if TYPE_CHECKING:  # importing synth.config first would be circular (config.schema imports it)
    from dynslam_cli.synth.config import SynthConfig

__all__ = ["PRESETS", "SynthResult", "render_preset", "intrinsics_for", "MOTION_THRESHOLD"]

MOTION_THRESHOLD = 0.005  # metres: an object moving more than this between frames is dynamic
FPS = 30.0  # frame rate of the rendered timestamps
EDGE_HOLES = True  # depth is dropped at depth discontinuities, like a structured-light sensor


@dataclass
class SynthResult:
    out_dir: Path
    preset: str
    frames: int
    width: int
    height: int
    seconds: float
    n_instances: int


def intrinsics_for(width: int, height: int) -> tuple[float, float, float, float]:
    """fx = fy = 525 at 640x480 scaled with the size; principal point at the image centre."""
    return (525.0 * width / 640.0, 525.0 * height / 480.0, (width - 1) / 2.0, (height - 1) / 2.0)


def _check(preset: str, cfg: SynthConfig, frames: int) -> None:
    if preset not in PRESETS:
        raise DynslamError(f"unknown synthetic preset '{preset}'; presets: {', '.join(PRESETS)}")
    if not (8 <= cfg.width <= 4096 and 8 <= cfg.height <= 4096):
        raise DynslamError(f"synth size {cfg.width}x{cfg.height} out of range (8..4096 per side)")
    if frames < 1:
        raise DynslamError(f"synth frames must be >= 1, got {frames}")
    if cfg.depth_noise < 0 or cfg.rgb_noise < 0:
        raise DynslamError(f"synth noise must be >= 0 (depth_noise={cfg.depth_noise}, rgb_noise={cfg.rgb_noise})")
    if not 0 <= cfg.depth_holes < 1:
        raise DynslamError(f"synth.depth_holes must be in [0, 1), got {cfg.depth_holes}")


def _check_out_dir(out_dir: Path) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise DynslamError(f"output path {out_dir} exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not (out_dir / "synth.json").is_file():
        raise DynslamError(f"output folder {out_dir} is not empty and holds no synthetic scene; "
                           "choose another --out")


class _Arrays:
    """Flat primitive arrays of a frame for the ray caster, grouped by object."""

    def __init__(self) -> None:
        self.groups: list[tuple[np.ndarray, float, int, int, int, int]] = []
        self.box = {k: [] for k in ("c", "R", "h", "tex", "scale", "inside", "inst")}
        self.ell = {k: [] for k in ("c", "R", "r", "tex", "scale", "inst")}

    def add(self, parts, inst: int, inside: bool = False, bound: bool = True, leaf: int = 4) -> None:
        """Add an object's primitives, split spatially into groups of at most ``leaf`` primitives
        (each with its bounding sphere) so that rays skip most of a detailed object."""
        if not bound:
            self._add_group(parts, range(len(parts.box_c)), range(len(parts.ell_c)), inst, inside, False)
            return
        for kind, n in (("box", len(parts.box_c)), ("ell", len(parts.ell_c))):
            centres = np.array(parts.box_c if kind == "box" else parts.ell_c).reshape(-1, 3)
            for idx in _split(centres, np.arange(n), leaf):
                self._add_group(parts, idx if kind == "box" else [], idx if kind == "ell" else [], inst, inside, True)

    def _add_group(self, parts, bi, ei, inst: int, inside: bool, bound: bool) -> None:
        from dynslam_cli.synth.geometry import Parts

        sub = Parts()
        for k in bi:
            sub.box(parts.box_c[k], parts.box_h[k], parts.box_R[k], parts.box_tex[k], parts.box_scale[k])
        for k in ei:
            sub.ellipsoid(parts.ell_c[k], parts.ell_r[k], parts.ell_R[k], parts.ell_tex[k], parts.ell_scale[k])
        if not sub.box_c and not sub.ell_c:
            return
        b0, e0 = len(self.box["c"]), len(self.ell["c"])
        self.box["c"] += sub.box_c
        self.box["R"] += sub.box_R
        self.box["h"] += sub.box_h
        self.box["tex"] += sub.box_tex
        self.box["scale"] += sub.box_scale
        self.box["inside"] += [inside] * len(sub.box_c)
        self.box["inst"] += [inst] * len(sub.box_c)
        self.ell["c"] += sub.ell_c
        self.ell["R"] += sub.ell_R
        self.ell["r"] += sub.ell_r
        self.ell["tex"] += sub.ell_tex
        self.ell["scale"] += sub.ell_scale
        self.ell["inst"] += [inst] * len(sub.ell_c)
        centre, radius = sub.bounding_sphere() if bound else (np.zeros(3), -1.0)
        self.groups.append((centre, radius, b0, len(self.box["c"]), e0, len(self.ell["c"])))

    def copy(self) -> "_Arrays":
        out = _Arrays()
        out.groups = list(self.groups)
        out.box = {k: list(v) for k, v in self.box.items()}
        out.ell = {k: list(v) for k, v in self.ell.items()}
        return out

    def pack(self):
        def arr(lst, shape, dtype):
            return np.ascontiguousarray(np.array(lst, dtype).reshape(shape))

        nb, ne = len(self.box["c"]), len(self.ell["c"])
        g = self.groups
        return (
            arr([x[0] for x in g], (-1, 3), np.float64), arr([x[1] for x in g], (-1,), np.float64),
            arr([(x[2], x[3]) for x in g], (-1, 2), np.int64), arr([(x[4], x[5]) for x in g], (-1, 2), np.int64),
            arr(self.box["c"], (nb, 3), np.float64), arr(self.box["R"], (nb, 3, 3), np.float64),
            arr(self.box["h"], (nb, 3), np.float64), arr(self.box["tex"], (nb, 6), np.int64),
            arr(self.box["scale"], (nb,), np.float64), arr(self.box["inside"], (nb,), np.bool_),
            arr(self.box["inst"], (nb,), np.int32),
            arr(self.ell["c"], (ne, 3), np.float64), arr(self.ell["R"], (ne, 3, 3), np.float64),
            arr(self.ell["r"], (ne, 3), np.float64), arr(self.ell["tex"], (ne,), np.int64),
            arr(self.ell["scale"], (ne,), np.float64), arr(self.ell["inst"], (ne,), np.int32),
        )


def _split(centres: np.ndarray, idx: np.ndarray, leaf: int) -> list[np.ndarray]:
    """Median splits along the widest axis until each chunk has at most ``leaf`` items."""
    if len(idx) == 0:
        return []
    if len(idx) <= leaf:
        return [idx]
    pts = centres[idx]
    axis = int(np.argmax(pts.max(axis=0) - pts.min(axis=0)))
    order = idx[np.argsort(pts[:, axis], kind="stable")]
    half = len(order) // 2
    return _split(centres, order[:half], leaf) + _split(centres, order[half:], leaf)


def _moving_flags(mover_parts: list[list], threshold: float) -> np.ndarray:
    """(n_movers, frames) bool: moved > threshold since the previous frame or before the next."""
    n_m = len(mover_parts)
    frames = len(mover_parts[0]) if n_m else 0
    flags = np.zeros((n_m, frames), bool)
    for m, seq in enumerate(mover_parts):
        pts = np.stack([p.markers() for p in seq])  # (frames, K, 3)
        step = np.linalg.norm(np.diff(pts, axis=0), axis=-1).max(axis=-1) > threshold  # (frames-1,)
        flags[m, 1:] |= step
        flags[m, :-1] |= step
    return flags


def _static_mesh(scene: Scene):
    import trimesh

    meshes = []
    for parts, inside in [(scene.room, True)] + [(o.parts, False) for o in scene.statics]:
        for c, R, h in zip(parts.box_c, parts.box_R, parts.box_h, strict=True):
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = c
            m = trimesh.creation.box(extents=2 * np.asarray(h), transform=T)
            if inside:
                m.invert()
            meshes.append(m)
    return trimesh.util.concatenate(meshes)


def _write_png(path: Path, img: np.ndarray) -> None:
    import cv2

    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise DynslamError(f"could not encode PNG {path}")
    path.write_bytes(buf.tobytes())


def render_preset(preset: str, out_dir: Path, cfg: SynthConfig, frames: int | None = None,
                  progress: bool = True) -> SynthResult:
    """Render the synthetic sequence ``preset`` into ``out_dir`` (replacing an earlier scene there)."""
    from tqdm import tqdm

    from dynslam_cli.synth.raycast import raycast
    from dynslam_cli.utils.io import atomic_path, default_mode, write_json_atomic, write_text_atomic

    start = time.perf_counter()
    n = int(cfg.frames if frames is None else frames)
    _check(preset, cfg, n)
    given = Path(out_dir)
    out_dir = given.resolve()
    if out_dir == Path.cwd().resolve() or out_dir.parent == out_dir:
        raise DynslamError(f"output folder {given} is the current or root folder; choose a new folder")
    _check_out_dir(out_dir)
    W, H, fps = int(cfg.width), int(cfg.height), FPS
    intr = intrinsics_for(W, H)
    scene = build_scene(preset, int(cfg.seed), n, fps, intr, W, H)
    times = np.arange(n) / fps
    stamps = [f"{t:.6f}" for t in times]

    static = _Arrays()
    static.add(scene.room, 0, inside=True, bound=False)
    for obj in scene.statics:
        static.add(obj.parts, obj.id)
    mover_parts = [[m.at(float(t)) for t in times] for m in scene.movers]
    moving = _moving_flags(mover_parts, MOTION_THRESHOLD)

    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        os.chmod(tmp, default_mode(folder=True))
        for sub in ("rgb", "depth", "instances", "dynamic"):
            (tmp / sub).mkdir()
        poses = []
        bar = tqdm(total=n, desc=f"synth {preset}", unit="frame", disable=not progress, file=sys.stderr)
        with ThreadPoolExecutor(max_workers=1) as pool:
            pending = []
            for i, t in enumerate(times):
                R, c = scene.camera(float(t))
                poses.append((R, c))
                arrays = static.copy()
                for m, mover in enumerate(scene.movers):
                    arrays.add(mover_parts[m][i], mover.id)
                depth, inst, rgb = raycast(
                    np.ascontiguousarray(R, np.float64), np.ascontiguousarray(c, np.float64),
                    intr[0], intr[1], intr[2], intr[3], W, H, *arrays.pack(),
                    scene.textures, np.asarray(scene.light, np.float64), float(scene.ambient),
                )
                rng = np.random.default_rng(np.random.SeedSequence([int(cfg.seed), PRESETS.index(preset), 7, i]))
                d16 = sense_depth(depth, rng, cfg.depth_noise, cfg.depth_holes, EDGE_HOLES, intr[0])
                rgb8 = sense_rgb(rgb, rng, cfg.rgb_noise)
                dyn_ids = [mv.id for m, mv in enumerate(scene.movers) if moving[m, i]]
                dyn = (np.isin(inst, dyn_ids) if dyn_ids else np.zeros(inst.shape, bool)).astype(np.uint8) * 255
                ts = stamps[i]
                pending.append(pool.submit(_write_frame, tmp, ts, rgb8, d16, inst.astype(np.uint16), dyn))
                if len(pending) > 4:
                    pending.pop(0).result()
                bar.update(1)
            for f in pending:
                f.result()
        bar.close()

        _write_lists(tmp, stamps, poses, write_text_atomic)
        with atomic_path(tmp / "static_mesh.ply") as p:
            _static_mesh(scene).export(p, file_type="ply", encoding="binary")
        instances = []
        for obj in scene.statics:
            box = obj.parts.aabb()
            instances.append({"id": obj.id, "name": obj.name, "kind": "static",
                              "aabb_first": _r(box), "aabb_last": _r(box)})
        for m, mover in enumerate(scene.movers):
            instances.append({"id": mover.id, "name": mover.name, "kind": "mover",
                              "aabb_first": _r(mover_parts[m][0].aabb()),
                              "aabb_last": _r(mover_parts[m][-1].aabb())})
        meta = {
            "preset": preset, "seed": int(cfg.seed), "size": [W, H], "fps": fps,
            "intrinsics": [round(v, 6) for v in intr], "depth_scale": DEPTH_SCALE, "frames": n,
            "sensor": {"depth_noise": cfg.depth_noise, "depth_holes": cfg.depth_holes,
                       "edge_holes": EDGE_HOLES, "rgb_noise": cfg.rgb_noise},
            "motion_threshold": MOTION_THRESHOLD,
            "instances": instances,
        }
        write_json_atomic(tmp / "synth.json", meta)
        _replace_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return SynthResult(out_dir=given, preset=preset, frames=n, width=W, height=H,
                       seconds=time.perf_counter() - start, n_instances=len(scene.statics) + len(scene.movers))


def _r(box: np.ndarray) -> list[list[float]]:
    return [[round(float(v), 6) for v in row] for row in box]


def _write_frame(root: Path, ts: str, rgb8, d16, inst16, dyn8) -> None:
    _write_png(root / "rgb" / f"{ts}.png", np.ascontiguousarray(rgb8[..., ::-1]))
    _write_png(root / "depth" / f"{ts}.png", d16)
    _write_png(root / "instances" / f"{ts}.png", inst16)
    _write_png(root / "dynamic" / f"{ts}.png", dyn8)


def _write_lists(root: Path, stamps, poses, write_text) -> None:
    from dynslam_cli.synth.geometry import rot_to_quat

    head = "# {} images\n# file: 'dynslam synth'\n# timestamp filename\n"
    write_text(root / "rgb.txt", head.format("color") + "".join(f"{s} rgb/{s}.png\n" for s in stamps))
    write_text(root / "depth.txt", head.format("depth") + "".join(f"{s} depth/{s}.png\n" for s in stamps))
    lines = ["# ground truth trajectory (camera-to-world, OpenCV optical frame)\n",
             "# file: 'dynslam synth'\n", "# timestamp tx ty tz qx qy qz qw\n"]
    for s, (R, c) in zip(stamps, poses, strict=True):
        q = rot_to_quat(R)
        lines.append(f"{s} " + " ".join(f"{v:.9f}" for v in (*c, *q)) + "\n")
    write_text(root / "groundtruth.txt", "".join(lines))


def _replace_dir(tmp: Path, out_dir: Path) -> None:
    """Move the finished temp folder onto out_dir (an earlier scene there is replaced)."""
    if out_dir.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
        try:
            os.replace(out_dir, old / "scene")
            try:
                os.replace(tmp, out_dir)
            except BaseException:
                os.replace(old / "scene", out_dir)
                raise
        except BaseException:
            if not (old / "scene").exists():  # the earlier scene is back in place
                shutil.rmtree(old, ignore_errors=True)
            raise
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, out_dir)
