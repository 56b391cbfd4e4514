"""The root configuration: one typed dataclass per part of the system.

Each part's dataclass lives in its own layer (``dynslam_cli/<layer>/config.py``) and carries a
help string per field; this module only composes them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from dynslam_cli.backend.config import BackendConfig
from dynslam_cli.data.config import DataConfig
from dynslam_cli.eval.config import EvalConfig
from dynslam_cli.map.config import MapConfig
from dynslam_cli.motion.config import MotionConfig
from dynslam_cli.run.config import RunConfig
from dynslam_cli.slam.config import MappingConfig, TrackingConfig
from dynslam_cli.synth.config import SynthConfig


@dataclass
class Config:
    data: DataConfig = field(default_factory=DataConfig, metadata={"help": "Reading sequences."})
    synth: SynthConfig = field(default_factory=SynthConfig, metadata={"help": "Synthetic scene rendering."})
    map: MapConfig = field(default_factory=MapConfig, metadata={"help": "The neural map."})
    tracking: TrackingConfig = field(default_factory=TrackingConfig, metadata={"help": "Camera tracking."})
    mapping: MappingConfig = field(default_factory=MappingConfig, metadata={"help": "Keyframes and bundle adjustment."})
    backend: BackendConfig = field(default_factory=BackendConfig, metadata={
        "help": "The keyframe backend (tracking.backend): landmarks, local bundle adjustment."})
    motion: MotionConfig = field(default_factory=MotionConfig, metadata={"help": "Learning to forget (dynamic mode)."})
    eval: EvalConfig = field(default_factory=EvalConfig, metadata={"help": "Evaluation."})
    run: RunConfig = field(default_factory=RunConfig, metadata={"help": "The run itself."})
