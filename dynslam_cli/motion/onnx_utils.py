"""onnxruntime sessions, the model cache folder, and model-file checks."""

from __future__ import annotations

import os
from pathlib import Path

from dynslam_cli.errors import DynslamError


def cache_dir() -> Path:
    """``$DYNSLAM_CACHE`` or ``~/.cache/dynslam`` (created)."""
    root = os.environ.get("DYNSLAM_CACHE") or str(Path.home() / ".cache" / "dynslam")
    p = Path(root).expanduser()
    p.mkdir(parents=True, exist_ok=True)
    return p


def require_model(path: str, what: str, how: str) -> Path:
    """The model file at ``path``, or a one-line DynslamError saying what is missing and how to get it."""
    if not path:
        raise DynslamError(f"{what}: no model file configured; {how}")
    p = Path(path).expanduser()
    if not p.is_file():
        raise DynslamError(f"{what}: model file not found: {p}; {how}")
    return p


def ort_session(path: str | Path, threads: int = 0):
    """An onnxruntime CPU (or CUDA when available) session; a corrupt file is a DynslamError."""
    try:
        import onnxruntime as ort
    except ImportError as exc:  # pragma: no cover - onnxruntime is a dependency
        raise DynslamError(f"onnxruntime is not installed (needed for {path}): pip install onnxruntime") from exc
    so = ort.SessionOptions()
    so.log_severity_level = 3
    if threads > 0:
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
    providers = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in ort.get_available_providers()]
    try:
        return ort.InferenceSession(str(path), sess_options=so, providers=providers)
    except Exception as exc:  # onnxruntime raises its own exception types
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DynslamError(f"cannot load ONNX model {path}: {msg}") from None
