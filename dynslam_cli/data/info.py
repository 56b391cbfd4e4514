"""`sequence_info`: what a sequence holds (frames, camera, depth statistics, ground truth)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np


@dataclass
class SequenceInfo:
    spec: str
    dataset: str
    name: str
    path: str
    frames: int  # after the cut
    total_pairs: int  # associated rgb/depth pairs before the cut
    width: int
    height: int
    intrinsics: list  # fx, fy, cx, cy
    distortion: list
    undistorted: bool  # frames are undistorted on load
    depth_scale: float
    duration_s: float  # last - first frame timestamp
    depth_sampled_frames: list = field(default_factory=list)  # indices of the sampled frames
    depth_valid_fraction: float = 0.0
    depth_min: float | None = None
    depth_median: float | None = None
    depth_max: float | None = None
    gt_frames: int = 0  # frames with a ground-truth pose
    groundtruth_file: str | None = None
    gt_poses_in_file: int = 0
    gt_time_span: list | None = None  # [first, last] timestamp of the ground-truth file
    has_gt_masks: bool = False
    has_instances: bool = False

    def to_dict(self) -> dict:
        return asdict(self)

    def format(self) -> str:
        fx, fy, cx, cy = self.intrinsics
        lines = [
            f"sequence     {self.dataset}/{self.name}  ({self.path})",
            f"frames       {self.frames} (of {self.total_pairs} associated pairs), {self.duration_s:.2f} s",
            f"resolution   {self.width}x{self.height}",
            f"intrinsics   fx {fx:.6g}  fy {fy:.6g}  cx {cx:.6g}  cy {cy:.6g}",
            (f"distortion   {', '.join(f'{d:.6g}' for d in self.distortion)}"
             f"{'  (undistorted on load)' if self.undistorted else ''}"),
        ]
        if self.depth_median is not None:
            lines.append(
                f"depth        valid {100 * self.depth_valid_fraction:.1f}%  min {self.depth_min:.3f} m  "
                f"median {self.depth_median:.3f} m  max {self.depth_max:.3f} m  "
                f"(over {len(self.depth_sampled_frames)} frames, scale 1/{self.depth_scale:g})")
        else:
            lines.append(f"depth        no valid depth in {len(self.depth_sampled_frames)} sampled frames")
        if self.groundtruth_file:
            span = self.gt_time_span
            span_txt = f", file spans {span[1] - span[0]:.2f} s" if span else ""
            lines.append(f"ground truth {self.gt_frames}/{self.frames} frames with a pose "
                         f"({self.gt_poses_in_file} poses in {self.groundtruth_file}{span_txt})")
        else:
            lines.append("ground truth none (no groundtruth.txt)")
        lines.append(f"gt masks     {'yes' if self.has_gt_masks else 'no'}"
                     f"{' (+ instance ids)' if self.has_instances else ''}")
        return "\n".join(lines) + "\n"


def sequence_info(spec: str, cfg=None, samples: int = 10, progress: bool = True) -> SequenceInfo:
    """Open ``spec`` and describe it; depth statistics over ``samples`` evenly spaced frames."""
    from dynslam_cli.data.open import open_sequence
    from dynslam_cli.data.tum import read_trajectory

    seq = open_sequence(spec, cfg, progress=progress)
    n = len(seq)
    idx = sorted(set(np.linspace(0, n - 1, num=min(samples, n)).round().astype(int).tolist()))
    valid_fracs, values = [], []
    for i in idx:
        d = seq.load_depth(i)
        v = d[d > 0]
        valid_fracs.append(v.size / d.size)
        values.append(v)
    allv = np.concatenate(values) if values else np.zeros(0, np.float32)
    ts = seq.timestamps
    gt_n, span = 0, None
    if seq.groundtruth_file is not None:
        gt_t, _ = read_trajectory(seq.groundtruth_file)
        gt_n = int(gt_t.size)
        span = [float(gt_t[0]), float(gt_t[-1])] if gt_t.size else None
    intr = seq.intrinsics
    return SequenceInfo(
        spec=str(spec), dataset=seq.dataset, name=seq.name, path=str(seq.path), frames=n,
        total_pairs=seq.total_pairs, width=intr.width, height=intr.height,
        intrinsics=intr.as_list(), distortion=list(seq.distortion), undistorted=seq.undistorted,
        depth_scale=seq.depth_scale, duration_s=float(ts[-1] - ts[0]) if n else 0.0,
        depth_sampled_frames=idx,
        depth_valid_fraction=float(np.mean(valid_fracs)) if valid_fracs else 0.0,
        depth_min=float(allv.min()) if allv.size else None,
        depth_median=float(np.median(allv)) if allv.size else None,
        depth_max=float(allv.max()) if allv.size else None,
        gt_frames=sum(p is not None for p in seq.gt_poses),
        groundtruth_file=str(seq.groundtruth_file) if seq.groundtruth_file else None,
        gt_poses_in_file=gt_n, gt_time_span=span,
        has_gt_masks=seq.has_gt_masks, has_instances=seq.has_instances,
    )
