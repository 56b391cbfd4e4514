"""A tiny analytic RGB-D scene (the inside of a textured box) for tests and quick checks.

``render(pose_c2w, intr)`` ray-casts the box exactly: depth is the z distance in the camera frame,
colour a per-wall checkerboard.  ``ToyFrame`` is one such frame for SLAM; ``write_sequence`` writes
frames as a synthetic scene folder (TUM layout + synth.json) that ``open_sequence`` reads.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dynslam_cli.geometry.camera import pixel_dirs
from dynslam_cli.geometry.lie import se3_exp_np

BOX = np.array([[-1.5, -1.2, -0.6], [1.5, 1.2, 3.0]])
WALL_COLOURS = np.array([[200, 60, 60], [60, 200, 60], [60, 60, 200], [200, 200, 60], [60, 200, 200], [200, 60, 200]],
                        np.float64)


class TinyIntrinsics:
    def __init__(self, width=64, height=48, f=None):
        self.width, self.height = int(width), int(height)
        self.fx = self.fy = float(f if f is not None else 0.8 * width)
        self.cx, self.cy = (width - 1) / 2, (height - 1) / 2

    @property
    def K(self):  # noqa: N802
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]])


def render(pose_c2w: np.ndarray, intr, box: np.ndarray = BOX):
    h, w = intr.height, intr.width
    vv, uu = np.mgrid[0:h, 0:w]
    dc = pixel_dirs(uu.ravel(), vv.ravel(), intr.fx, intr.fy, intr.cx, intr.cy).astype(np.float64)
    d = dc @ pose_c2w[:3, :3].T
    o = pose_c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = (box[1] - o) / d
        t_lo = (box[0] - o) / d
    t_axis = np.where(d > 0, t_hi, t_lo)
    t_axis = np.where(np.isfinite(t_axis) & (t_axis > 0), t_axis, np.inf)
    axis = t_axis.argmin(1)
    t = t_axis[np.arange(len(t_axis)), axis]
    p = o + d * t[:, None]
    wall = axis * 2 + (d[np.arange(len(d)), axis] > 0)
    # checkerboard on the two in-plane coordinates
    uvw = np.floor(p * 3.0).astype(int)
    parity = (uvw.sum(1) - uvw[np.arange(len(uvw)), axis]) % 2
    col = WALL_COLOURS[wall] * (0.55 + 0.45 * parity[:, None])
    col = col * (0.8 + 0.2 * np.cos(p[:, :1] * 2.1 + p[:, 1:2] * 1.3))
    depth = (t).astype(np.float32).reshape(h, w)  # t along a z=1 camera direction = camera depth
    return col.clip(0, 255).astype(np.uint8).reshape(h, w, 3), depth


class ToyFrame:
    """Frame ``i`` of the toy scene seen from ``pose`` (the reader's ``Frame`` fields SLAM uses);
    ``with_gt`` False leaves out the ground-truth pose."""

    def __init__(self, i: int, pose: np.ndarray, intr, with_gt: bool = True):
        self.index, self.timestamp = i, float(i)
        self.rgb, self.depth = render(pose, intr)
        self.pose_c2w = pose if with_gt else None


def first_frame_state(cfg, intr) -> dict:
    """``state_dict()`` of a SLAM that processed the toy scene's first frame (identity pose): a
    fitted map for tests to load."""
    import torch

    from dynslam_cli.slam.system import SLAM

    slam = SLAM(cfg, intr, torch.device("cpu"))
    slam.process(ToyFrame(0, np.eye(4), intr))
    return slam.state_dict()


def load_slam(cfg, intr, state: dict):
    """A CPU SLAM resumed from ``state``."""
    import torch

    from dynslam_cli.slam.system import SLAM

    slam = SLAM(cfg, intr, torch.device("cpu"))
    slam.load_state_dict(state)
    return slam


def trajectory(n: int, step: float = 0.01, rot_step: float = 0.004) -> np.ndarray:
    """A smooth camera path: translation and a slow yaw, starting at the origin looking +z."""
    poses = []
    for i in range(n):
        xi = np.array([step * i, 0.3 * step * i, 0.5 * step * np.sin(i / 5), 0.0, rot_step * i, 0.5 * rot_step * i])
        poses.append(se3_exp_np(xi))
    return np.stack(poses)


def write_sequence(folder: Path, n: int = 6, width: int = 80, height: int = 60, step: float = 0.01) -> Path:
    """Write ``n`` frames as a synthetic scene folder readable by ``open_sequence``."""
    import cv2

    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    intr = TinyIntrinsics(width, height)
    poses = trajectory(n, step)
    rgb_lines, depth_lines, gt_lines = ["# rgb"], ["# depth"], ["# timestamp tx ty tz qx qy qz qw"]
    from scipy.spatial.transform import Rotation

    for i, T in enumerate(poses):
        ts = f"{1.0 + i / 30:.6f}"
        rgb, depth = render(T, intr)
        cv2.imwrite(str(folder / "rgb" / f"{ts}.png"), rgb[..., ::-1])
        cv2.imwrite(str(folder / "depth" / f"{ts}.png"), np.round(depth * 5000).astype(np.uint16))
        rgb_lines.append(f"{ts} rgb/{ts}.png")
        depth_lines.append(f"{ts} depth/{ts}.png")
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        gt_lines.append(f"{ts} {T[0, 3]:.7f} {T[1, 3]:.7f} {T[2, 3]:.7f} {q[0]:.7f} {q[1]:.7f} {q[2]:.7f} {q[3]:.7f}")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (folder / "groundtruth.txt").write_text("\n".join(gt_lines) + "\n")
    meta = {"preset": "toybox", "seed": 0, "size": [width, height], "width": width, "height": height,
            "intrinsics": [intr.fx, intr.fy, intr.cx, intr.cy], "depth_scale": 5000.0, "fps": 30,
            "instances": [], "room": BOX.tolist()}
    (folder / "synth.json").write_text(json.dumps(meta))
    return folder


def tiny_config(**overrides):
    """A small, fast configuration for the toy scene (tests): few levels, small tables, few rays;
    dense tracking against the neural map (the keyframe backend has its own tests: a 48x36 frame
    holds too few ORB keypoints for it)."""
    from dynslam_cli.config import Config, apply_overrides

    cfg = Config()
    sets = {
        "run.mode": "static", "tracking.backend": False, "map.n_levels": 6, "map.log2_hashmap_size": 14,
        "map.voxel_size": 0.05, "map.bounds": [[-1.7, -1.4, -0.8], [1.7, 1.4, 3.2]],
        "tracking.ignore_border": 2, "tracking.n_rays": 256, "tracking.iters": 10,
        "mapping.first_iters": 100, "mapping.n_rays": 512, "mapping.iters": 5,
    }
    sets.update(overrides)
    cfg = apply_overrides(cfg, [f"{k}={v}" for k, v in sets.items()])
    cfg.map.BASE_RESOLUTION = 8  # a coarser first level for the small box (a constant, shadowed on this instance)
    return cfg
