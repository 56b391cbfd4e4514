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
    still_seconds: float = opt(0.67, "Dynamic mode: an instance whose 3-D points every keyframe of the last this-many "
                               "seconds (in frames at the sequence's frame rate) saw at the same depth (within "
                               "run.still_tolerance) has stayed put and is labelled static (with "
                               "motion.centre_feature over half as long, at its place); 0 = off.", min=0)
    still_tolerance: float = opt(0.05, "Dynamic mode: how close (m) an instance's points must lie to the depth the "
                                 "keyframes saw for run.still_seconds to count it as stayed put; 0 = "
                                 "motion.depth_threshold.", min=0)
    forget_radius: float = opt(0.05, "Dynamic mode: keyframe rays within this distance (m) of the surface of something "
                               "the backward check saw leave are forgotten for good (a departed object the classifier "
                               "does not recognise in its keyframe crops), and the mesh leaves out surfaces the newest "
                               "keyframe looking at them saw through (by more than this distance near where the "
                               "check saw something leave, else by the truncation); 0 = off (the paper forgets "
                               "through the classifier only).", min=0)
