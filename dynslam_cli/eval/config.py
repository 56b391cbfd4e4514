"""Configuration of evaluation."""

from __future__ import annotations

from dataclasses import dataclass

from dynslam_cli.config.fields import opt


@dataclass
class EvalConfig:
    max_time_diff: float = opt(0.02, "Maximum timestamp difference (s) when associating estimate and ground truth.", above=0)
    align: str = opt("se3", "Trajectory alignment: se3 (Umeyama, no scale), sim3, origin, none.",
                     choices=("se3", "sim3", "origin", "none"))
    mesh_samples: int = opt(200000, "Points sampled on each mesh for accuracy/completion.", min=1)
    completion_threshold: float = opt(0.05, "Distance (m) under which a reference point counts as completed.", above=0)
    seed: int = opt(0, "Seed of the point sampling on meshes (results are repeatable).", min=0)
    cull_views: int = opt(200, "Camera poses (evenly spread) whose frusta cull the reference for completion.", min=1)
    cull_max_depth: float = opt(5.0, "Frustum depth (m) when culling the reference to the observed space.", above=0)
