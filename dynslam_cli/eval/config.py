"""Configuration of evaluation."""

from __future__ import annotations

from dataclasses import dataclass

from dynslam_cli.config.fields import opt


@dataclass
class EvalConfig:
    max_time_diff: float = opt(0.02, "Maximum timestamp difference (s) when associating estimate and ground truth.", above=0)
    align: str = opt("se3", "Trajectory alignment: se3 (Umeyama, no scale), sim3, origin, none.",
                     choices=("se3", "sim3", "origin", "none"))
    completion_threshold: float = opt(0.05, "Distance (m) under which a reference point counts as completed.", above=0)
