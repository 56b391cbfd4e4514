"""Helpers for the data-layer tests: tiny TUM-layout / synthetic folders written on the fly.
(No tests here; imported by the other tests/test_data_*.py files.)"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def quat_z(angle: float) -> tuple[float, float, float, float]:
    """(qx, qy, qz, qw) of a rotation about z."""
    return (0.0, 0.0, float(np.sin(angle / 2)), float(np.cos(angle / 2)))


def make_folder(path: Path, n: int = 5, w: int = 32, h: int = 24, *, rgb_ts=None, depth_ts=None,
                gt_ts=None, synth: dict | None = None, masks: bool = False, depth_scale: float = 5000.0,
                stamp_fmt: str = "{:.6f}", seed: int = 0) -> Path:
    """Write a TUM-layout folder: rgb/, depth/ (uint16 PNG), rgb.txt, depth.txt, groundtruth.txt
    (translation x = timestamp, rotation about z by timestamp radians), optionally synth.json
    and instances/ + dynamic/ masks named by the rgb timestamps."""
    import cv2

    path = Path(path)
    rng = np.random.default_rng(seed)
    rgb_ts = [0.1 * i for i in range(n)] if rgb_ts is None else list(rgb_ts)
    depth_ts = list(rgb_ts) if depth_ts is None else list(depth_ts)
    for sub in ("rgb", "depth"):
        (path / sub).mkdir(parents=True, exist_ok=True)
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth maps"]
    for i, t in enumerate(rgb_ts):
        s = stamp_fmt.format(t)
        img = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        img[0, 0] = (i, 0, 255)  # RGB marker: written as BGR below
        cv2.imwrite(str(path / "rgb" / f"{s}.png"), img[:, :, ::-1])
        rgb_lines.append(f"{s} rgb/{s}.png")
        if masks:
            (path / "instances").mkdir(exist_ok=True)
            (path / "dynamic").mkdir(exist_ok=True)
            inst = np.zeros((h, w), np.uint16)
            inst[: h // 2, : w // 2] = 3
            inst[h // 2:, w // 2:] = 700 + i
            dyn = np.zeros((h, w), np.uint8)
            dyn[h // 2:, w // 2:] = 255
            cv2.imwrite(str(path / "instances" / f"{s}.png"), inst)
            cv2.imwrite(str(path / "dynamic" / f"{s}.png"), dyn)
    for i, t in enumerate(depth_ts):
        s = stamp_fmt.format(t)
        d = np.full((h, w), 1.0 + 0.1 * i, np.float64)
        d[:, w // 2:] = 3.0
        d[1, 1] = 0.0  # a hole
        cv2.imwrite(str(path / "depth" / f"{s}.png"), np.round(d * depth_scale).astype(np.uint16))
        depth_lines.append(f"{s} depth/{s}.png")
    (path / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (path / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    gt_ts = list(rgb_ts) if gt_ts is None else list(gt_ts)
    if gt_ts:
        lines = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
        for t in gt_ts:
            q = quat_z(t)
            lines.append(f"{t:.6f} {t:.6f} 0 0 {q[0]} {q[1]} {q[2]} {q[3]}")
        (path / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    if synth is not None:
        meta = {"preset": "test", "seed": seed, "size": [w, h], "depth_scale": depth_scale,
                "fps": 10, "instances": []}
        meta.update(synth)
        (path / "synth.json").write_text(json.dumps(meta))
    return path


def data_cfg(**data):
    """A default Config with data.* overrides."""
    from dynslam_cli.config import Config

    cfg = Config()
    for k, v in data.items():
        setattr(cfg.data, k, v)
    return cfg
