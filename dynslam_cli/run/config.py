"""Configuration of a run."""

from __future__ import annotations

from dataclasses import dataclass

from dynslam_cli.config.fields import opt


@dataclass
class RunConfig:
    mode: str = opt("dynamic", "dynamic (learn to forget) or static (the Co-SLAM baseline).", choices=("dynamic", "static"))
    device: str = opt("auto", "auto (cuda when available), cpu or cuda.", choices=("auto", "cpu", "cuda"))
    seed: int = opt(0, "Random seed (torch, numpy, ray sampling).", min=0)
    threads: int = opt(0, "Torch/numba threads; 0 = all cores.", min=0)
    checkpoint_every: int = opt(50, "Write a resumable checkpoint every N frames; 0 = never.", min=0)
    save_masks: bool = opt(False, "Save per-frame motion masks as PNG.")
    mesh: bool = opt(True, "Extract the mesh at the end.")
    mesh_resolution: float = opt(0.02, "Marching-cubes voxel size (m).", above=0)
    results_root: str = opt("results/runs", "Folder under which run folders are created.")
    keep_checkpoint: bool = opt(False, "Keep checkpoint.pt after a completed run (it is removed by default).")
    stop_after: int = opt(0, "Stop (status 'interrupted') after processing this many frames in this call; 0 = never. "
                             "For tests of --resume.", min=0)
    check_radius: int = opt(1, "Dynamic mode: a pixel is inconsistent only when no rendered depth within this many "
                               "pixels (at check resolution) agrees with the observation; 0 = the plain per-pixel check.", min=0)
    check_warmup: int = opt(5, "Dynamic mode: no inconsistency check before this frame (the map needs a keyframe "
                               "and a bundle adjustment beyond frame 0 to judge anything).", min=0)
    check_occlusion: bool = opt(True, "Dynamic mode: 'observed in front of the map' counts only where some recent "
                                "keyframe saw the point or the free space at it, not an occluder in front of it "
                                "(newly revealed space is unknown to the map).")
    retrack_fraction: float = opt(0.02, "Dynamic mode: when a classifier update newly marks more than this fraction of "
                                  "the frame's valid pixels dynamic, the frame is tracked again without them "
                                  "(the paper tracks once); 0 = never.", min=0, max=1)
    still_frames: int = opt(10, "Dynamic mode with motion.centre_feature: an instance whose 3-D points every keyframe of "
                            "the last this-many frames (two or more) saw at the same depth has stayed put and is "
                            "labelled static at its place, whatever the map says; 0 = off.",
                            min=0, check=(lambda v: v != 1, "not 1 (0 = off, else two or more)"))
    still_without_centre: bool = opt(False, "Dynamic mode: apply run.still_frames without motion.centre_feature too (an "
                                     "instance that stayed put is labelled static, which the classifier then learns "
                                     "for its appearance everywhere): breaks the loop where a surface once labelled "
                                     "dynamic is never mapped, so always looks 'in front of the map'.")
    still_tolerance: float = opt(0.0, "Dynamic mode without motion.centre_feature (run.still_without_centre): how close "
                                 "(m) an instance's points must lie to the depth the keyframes saw for "
                                 "run.still_frames to count it as stayed put; 0 = motion.depth_threshold.", min=0)
    still_tolerance_centre: float = opt(0.0, "The same with motion.centre_feature, where 'static' is learnt at the "
                                        "instance's place only; 0 = motion.depth_threshold.", min=0)
    still_frames_centre: int = opt(0, "run.still_frames with motion.centre_feature (a shorter window costs less where "
                                      "'static' is learnt at the place only); 0 = run.still_frames.",
                                      min=0, check=(lambda v: v != 1, "not 1 (0 = run.still_frames, else two or more)"))
    forget_radius: float = opt(0.05, "Dynamic mode: keyframe rays within this distance (m) of the surface of something "
                               "the backward check saw leave are forgotten for good (a departed object the classifier "
                               "does not recognise in its keyframe crops); 0 = off (the paper forgets through the "
                               "classifier only).", min=0)
    carve_margin: float = opt(0.0, "Dynamic mode: at each new keyframe, earlier keyframe rays along which the scene "
                              "changed by more than this (m) are forgotten for good, whatever the classifier says: "
                              "the new keyframe's static depth sees through their surface point (it left), or sees "
                              "a surface in the free space they crossed (something arrived); 0 = off.", min=0)
