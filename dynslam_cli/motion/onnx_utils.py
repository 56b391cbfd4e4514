"""onnxruntime sessions, the model cache folder, and model-file checks (file, inputs, outputs)."""

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


def ort_session(path: str | Path, threads: int = 0, device: str = "cpu"):
    """An onnxruntime session on the CPU, or on CUDA where ``device`` is ``cuda`` and this onnxruntime has
    its CUDA provider (the ``onnxruntime-gpu`` package); a corrupt file is a DynslamError."""
    try:
        import onnxruntime as ort
    except ImportError as exc:  # pragma: no cover - onnxruntime is a dependency
        raise DynslamError(f"onnxruntime is not installed (needed for {path}): pip install onnxruntime") from exc
    so = ort.SessionOptions()
    so.log_severity_level = 3
    if threads > 0:
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
    # no spin-waiting between operators: the session runs beside the run's torch work (run/ahead.py), whose cores a
    # spinning pool thread would take
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    wanted = ("CUDAExecutionProvider", "CPUExecutionProvider") if device == "cuda" else ("CPUExecutionProvider",)
    providers = [p for p in wanted if p in ort.get_available_providers()]
    try:
        return ort.InferenceSession(str(path), sess_options=so, providers=providers)
    except Exception as exc:  # onnxruntime raises its own exception types
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DynslamError(f"cannot load ONNX model {path}: {msg}") from None


def _dims(shape) -> str:
    return "×".join(str(d) if isinstance(d, int) else (str(d) if d else "?") for d in (shape or [])) or "scalar"


def describe_io(session) -> str:
    """``inputs images[1×3×640×640]; outputs output0[1×37×8400], output1[1×32×160×160]``."""
    ins = ", ".join(f"{i.name}[{_dims(i.shape)}]" for i in session.get_inputs()) or "none"
    outs = ", ".join(f"{o.name}[{_dims(o.shape)}]" for o in session.get_outputs()) or "none"
    return f"inputs {ins}; outputs {outs}"


def check_image_input(session, path, what: str, expected: str) -> None:
    """The first input must be a float N×3×H×W image batch (dimensions may be symbolic)."""
    ins = session.get_inputs()
    inp = ins[0] if ins else None
    shape = list(inp.shape or []) if inp is not None else []
    ok = (inp is not None and len(shape) == 4 and fixed(shape[1]) in (3, None)
          and inp.type == "tensor(float)")
    if not ok:
        raise DynslamError(f"{what}: {path} is not a model of the expected kind: it has {describe_io(session)} "
                           f"(input types: {', '.join(i.type for i in ins) or 'none'}); expected {expected}")


def fixed(d) -> int | None:
    """A fixed dimension, or None for a symbolic one."""
    return d if isinstance(d, int) and d > 0 else None
