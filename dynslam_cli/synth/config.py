"""Configuration of the synthetic scene renderer."""

from __future__ import annotations

from dataclasses import dataclass

from dynslam_cli.config.fields import opt


@dataclass
class SynthConfig:
    width: int = opt(640, "Image width in pixels.", min=8, max=4096)
    height: int = opt(480, "Image height in pixels.", min=8, max=4096)
    frames: int = opt(150, "Frames rendered when `synth/NAME` is first used.", min=1)
    seed: int = opt(0, "Random seed of textures, trajectories and noise.", min=0)
    depth_noise: float = opt(0.002, "Depth noise std at 1 m (m); grows with depth squared like a Kinect.", min=0)
    depth_holes: float = opt(0.01, "Fraction of depth pixels dropped at random (holes).", min=0, below=1)
    rgb_noise: float = opt(2.0, "Gaussian colour noise std (0-255 scale).", min=0)
