"""Configuration of tracking and mapping (Co-SLAM TUM settings, see BRIEF.md)."""

from __future__ import annotations

from dataclasses import dataclass

from dynslam_cli.config.fields import opt


@dataclass
class TrackingConfig:
    backend: bool = opt(True, "Poses from the keyframe backend (dynslam_cli/backend: ORB landmarks on static pixels, "
                        "robust pose-only tracking, gtsam local bundle adjustment); the neural map then trains on "
                        "those poses without moving them. Off: Co-SLAM's dense tracking against the neural map "
                        "(tracking.iters) and pose refinement in its bundle adjustment (the paper / coslam presets).")
    iters: int = opt(10, "Adam iterations per frame of dense tracking against the neural map, when tracking.backend "
                     "is off or the backend lost the frame (20 for harder sequences).", min=0)
    n_rays: int = opt(1024, "Rays sampled per tracking iteration (|H_t|).", min=1)
    lr: float = opt(0.01, "Adam learning rate of the 6-DoF pose increment.", above=0)
    ignore_border: int = opt(20, "Pixels ignored at the image border when sampling rays.", min=0)
    icp_init: bool = opt(True, "Without the backend: refine the constant-velocity initial guess by coarse-to-fine "
                         "point-to-plane ICP of the depth against the previous frame's depth.")


@dataclass
class MappingConfig:
    every: int = opt(5, "Run bundle adjustment every N frames.", min=1)
    keyframe_every: int = opt(5, "Insert a keyframe every N frames.", min=1)
    keyframe_ray_fraction: float = opt(0.05, "Fraction of a keyframe's pixels stored for replay.", above=0, max=1)
    iters: int = opt(20, "Bundle adjustment iterations.", min=0)
    n_rays: int = opt(2048, "Rays per bundle adjustment iteration (|H_b|).", min=1)
    lr_map: float = opt(0.01, "Learning rate of the grid and decoders.", above=0)
    lr_pose: float = opt(0.001, "Learning rate of keyframe poses in bundle adjustment, without the backend (with it "
                         "the backend's poses stand); 0 = the map only.", min=0)
    first_iters: int = opt(50, "Mapping iterations on the first frame (Co-SLAM: 1000; the presets coslam and paper "
                           "keep that, as their dense tracking starts from the first frame's map).", min=0)
    final_iters: int = opt(0, "Bundle adjustment iterations over all keyframes (and the last frame) after the last "
                           "frame, before the trajectory is written (SLAM.finish); 0 = none (Co-SLAM).", min=0)
