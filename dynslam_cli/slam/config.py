"""Configuration of tracking and mapping (Co-SLAM TUM settings, see BRIEF.md)."""

from __future__ import annotations

from dataclasses import dataclass

from dynslam_cli.config.fields import numbers, opt


@dataclass
class TrackingConfig:
    backend: bool = opt(True, "Poses from the keyframe backend (dynslam_cli/backend: ORB landmarks on static pixels, "
                        "robust pose-only tracking, gtsam local bundle adjustment); the neural map then trains on "
                        "those poses without moving them. Off: Co-SLAM's dense tracking against the neural map "
                        "(tracking.iters) and pose refinement in its bundle adjustment (the paper / coslam presets).")
    iters: int = opt(10, "Adam iterations per frame of dense tracking against the neural map, when tracking.backend "
                     "is off (20 for harder sequences).", min=0)
    iters_dynamic: int = opt(-1, "Adam iterations per frame in dynamic mode; -1 = iters.  bonn.yaml sets 0 (the feature "
                             "init's pose is kept): on the crowd clip, dense tracking against a map that still holds "
                             "people the masks missed pulled it away (25.1 cm ATE with 10 iterations, 5.5 with 0).",
                             min=0, also=(-1,))
    n_rays: int = opt(1024, "Rays sampled per tracking iteration (|H_t|).", min=1)
    lr: float = opt(0.01, "Adam learning rate of the 6-DoF pose increment.", above=0)
    ignore_border: int = opt(20, "Pixels ignored at the image border when sampling rays.", min=0)
    const_velocity: bool = opt(True, "Initialise each pose with the constant-velocity model.")
    max_jump: float = opt(0.3, "A tracked pose moving more than this (m) from its initial guess is divergence; a feature "
                          "or ICP initial guess farther than this from the constant-velocity one is not used.", above=0)
    keep_best: bool = opt(True, "Return the lowest-loss pose seen (else the last iterate; Co-SLAM's TUM config uses the last).")
    resample_rays: bool = opt(True, "Draw new rays every iteration (Co-SLAM); false = one ray set per frame, so losses compare.")
    min_pixels: int = opt(50, "Fewer usable pixels than this: tracking is skipped (constant-velocity pose, logged).", min=0)
    icp_init: bool = opt(True, "Refine the initial guess by coarse-to-fine point-to-plane ICP of the depth against the "
                         "previous frame's depth (starting from the constant-velocity guess); with feature_init only "
                         "where the feature init fails.")
    icp_factors: list = opt([8, 4, 2], "ICP pyramid: downsampling factors, coarse to fine (640x480 -> 80x60, 160x120, 320x240).")
    icp_iters: list = opt([8, 5, 3], "Gauss-Newton iterations per ICP level.")
    icp_max_points: int = opt(0, "ICP: at most about this many current points per pyramid level (an even stride; "
                              "the reference stays whole); 0 = all. 20000 halves ICP time but cost 0.1-0.4 cm ATE on "
                              "Bonn crowd frames 0-39.", min=0)
    icp_max_dist: float = opt(0.1, "ICP: associations farther apart than this (m) are rejected.", above=0)
    icp_min_fraction: float = opt(0.2, "ICP result is ignored (constant-velocity guess kept) when fewer of the current "
                                  "points associate.", min=0, max=1)
    feature_init: bool = opt(False, "Initial guess from ORB keypoints matched to a reference frame and solved by PnP "
                             "with RANSAC (static pixels only; depth beyond data.max_depth included); ICP then runs only "
                             "where it fails. Beyond Co-SLAM, on in bonn.yaml: where the static depth is nearly "
                             "degenerate the texture fixes the pose. Off elsewhere: on the synthetic scenes' exact depth "
                             "ICP is better (synth static 1.26 cm with it against 0.62 without; walker 2.74 against 1.09).")
    feature_count: int = opt(2000, "Feature init: ORB keypoints per frame.", min=1)
    feature_ratio: float = opt(0.8, "Feature init: Lowe's ratio test of the two nearest descriptors.", above=0, max=1)
    feature_ransac_px: float = opt(2.0, "Feature init: RANSAC inlier reprojection error in pixels (at 640 px width).", above=0)
    feature_min_inliers: int = opt(20, "Feature init: fewer PnP inliers than this and the guess is not used.", min=0)
    feature_min_inlier_ratio: float = opt(0.0, "Feature init: fewer PnP inliers than this fraction of the previous "
                                          "frame's and the guess is not used (ICP then; the next frame compares with "
                                          "this one's count); 0 = off. Bonn crowd clip, geometric, 8 references: 0.5 "
                                          "gave 4.59 / 2.69 / 2.89 cm at seeds 0-2 against 3.01 / 54.3 (lost at "
                                          "frame 82) / 2.65 off; yolo-person.yaml 3.32 against 2.61.", min=0, max=1)
    feature_verify: float = opt(0.0, "Feature init: a PnP step farther than this (m) from the constant-velocity step "
                                "is used only if it fits the map at least as well (median SDF residual of the "
                                "frame's static rays at both poses); 0 = off. bonn.yaml sets 0.1: on the crowd clip "
                                "(geometric, seed 1) a 0.215 m PnP step from 106 inliers lost the camera (54.3 cm "
                                "ATE) without it, 2.69 cm with it.", min=0)
    feature_verify_min_static: float = opt(0.0, "tracking.feature_verify: a far PnP step is refused outright when "
                                           "fewer than this fraction of the frame's pixels are static with depth "
                                           "(too little of the map in view to judge it); 0 = off.", min=0, max=1)
    feature_keep_ref: float = opt(0.15, "Feature init: frames are matched to one reference frame while they share at "
                                  "least this fraction of its keypoints with depth as inliers; below it the frame "
                                  "just tracked becomes the reference (fewer, longer baselines drift less than "
                                  "frame-to-frame chaining).", min=0, max=1)
    feature_refs: int = opt(1, "Feature init: PnP runs on the keypoints of up to this many reference frames at once (a "
                            "local map, lifted with their current poses); 1 = one reference. Chained PnP alone on the "
                            "Bonn crowd clip with person masks: 1.9-3.1 cm ATE with 5-10 references against 2.6-6.9 "
                            "with one, across reference-switch thresholds; but with dense tracking on top (static "
                            "mode, frames 0-39) 8 references scored 2.43 / 2.41 cm against 1.54 / 1.85 with one.", min=1)
    feature_refs_dynamic: int = opt(-1, "Feature init: tracking.feature_refs in dynamic mode; -1 = feature_refs. "
                                    "bonn.yaml sets 8: dynamic mode there keeps the feature pose (iters_dynamic 0), and "
                                    "the local map of 8 references gave 2.61 cm with yolo-seg against 3.89 with one.",
                                    min=1, also=(-1,))
    edge_margin: int = opt(2, "Do not sample tracking rays within this many pixels of a depth discontinuity (a step "
                           "of >5 % at 540 px focal length, or a hole): the map blurs edges, and on real depth they "
                           "bias the pose; 0 = sample them.", min=0)

    def validate(self, key):
        """Cross-field and list rules (see config.fields)."""
        factors, iters = numbers(self.icp_factors), numbers(self.icp_iters)
        if factors is None or not all(f >= 1 and f == int(f) for f in factors):
            yield f"{key('icp_factors')} must be a list of integers >= 1 (got {self.icp_factors!r})"
        elif iters is None or not all(i >= 0 and i == int(i) for i in iters):
            yield f"{key('icp_iters')} must be a list of integers >= 0 (got {self.icp_iters!r})"
        elif len(iters) != len(factors):
            yield (f"{key('icp_iters')} must have one entry per {key('icp_factors')} level "
                   f"(got {len(iters)} for {len(factors)})")



@dataclass
class MappingConfig:
    every: int = opt(5, "Run bundle adjustment every N frames.", min=1)
    keyframe_every: int = opt(5, "Insert a keyframe every N frames.", min=1)
    keyframe_ray_fraction: float = opt(0.05, "Fraction of a keyframe's pixels stored for replay.", above=0, max=1)
    iters: int = opt(20, "Bundle adjustment iterations.", min=0)
    n_rays: int = opt(2048, "Rays per bundle adjustment iteration (|H_b|).", min=1)
    lr_map: float = opt(0.01, "Learning rate of the grid and decoders.", above=0)
    lr_pose: float = opt(0.001, "Learning rate of keyframe poses.", min=0)
    lr_pose_dynamic: float = opt(-1.0, "mapping.lr_pose in dynamic mode; -1 = lr_pose.  bonn.yaml sets 0 (bundle "
                                 "adjustment refines the map only): moving the poses against the nearly degenerate "
                                 "static map of the crowd clip added 1-1.5 cm ATE.", min=0, also=(-1,))
    first_iters: int = opt(1000, "Mapping iterations on the first frame.", min=0)
    first_rays: int = opt(2048, "Rays per mapping iteration on the first frame.", min=1)
    edge_margin: int = opt(2, "Keyframe and current-frame mapping rays avoid pixels within this many pixels of a depth "
                           "discontinuity; 0 = use them.", min=0)
    min_rays_current: int = opt(100, "At least this many of the BA rays come from the current frame (Co-SLAM min_pixels_cur).",
                                min=0)
    pose_accum_steps: int = opt(5, "Bundle adjustment steps the pose optimiser once every N iterations on the gradients "
                                "summed over them (Co-SLAM pose_accum_step); the map steps every iteration.", min=1)
    optimize_current: bool = opt(True, "Also refine the current frame's pose in bundle adjustment (Co-SLAM optim_cur).")
    fix_first_pose: bool = opt(True, "Keep the first keyframe's pose fixed in bundle adjustment.")
    final_iters: int = opt(0, "Bundle adjustment iterations over all keyframes (and the last frame) after the last "
                           "frame, before the trajectory is written (SLAM.finish); 0 = none (Co-SLAM).  200 gained "
                           "0.12-0.20 cm ATE on Bonn crowd frames 0-39 at seeds 0-2 (1000: 0.13 cm worse).", min=0)
