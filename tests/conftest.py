"""Shared fixtures. Real data lives in ../shared (read in place, never copied); tests that need
it skip with a clear message where it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True, scope="module")
def restore_threads():
    """Tests that run SLAM set torch's thread count (run.threads); put it back after each module."""
    import torch

    old = torch.get_num_threads()
    yield
    torch.set_num_threads(old)


def shared_root() -> Path:
    return Path(os.environ.get("DYNSLAM_SHARED", REPO.parent / "shared"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    root = shared_root()
    if not root.is_dir():
        pytest.skip(f"real data not available: {root} is absent (set DYNSLAM_SHARED to its location)")
    return root


@pytest.fixture(scope="session")
def bonn_clip(shared_dir: Path) -> Path:
    p = shared_dir / "data" / "bonn_crowd_150_449_s2"
    if not p.is_dir():
        pytest.skip(f"real Bonn clip not available at {p}")
    return p


@pytest.fixture(scope="session")
def tum_clip(shared_dir: Path) -> Path:
    p = shared_dir / "data" / "tum_fr1_desk_9"
    if not p.is_dir():
        pytest.skip(f"real TUM frames not available at {p}")
    return p


@pytest.fixture(scope="session")
def yolo_model(shared_dir: Path) -> Path:
    p = shared_dir / "models" / "yolov8n-seg_deq_fp32.onnx"
    if not p.is_file():
        pytest.skip(f"YOLOv8n-seg ONNX not available at {p}")
    return p
