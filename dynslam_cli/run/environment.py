"""What a run ran on, for run.json and timing.json: library versions, the CPU's model, on CUDA the
GPU's name and CUDA's version (float results, so trajectories, differ between builds, CPUs and
GPUs: README, "Reproducibility"), and the process's peak resident memory."""

from __future__ import annotations

import importlib.metadata
import os
import platform
import resource
import sys
from pathlib import Path

import numpy as np

from dynslam_cli.run import checkpoint
from dynslam_cli.utils.io import proc_status


def versions(device=None) -> dict:
    """Library versions, the CPU's model and, on a CUDA device, the GPU's name and CUDA's version."""
    import torch

    out = {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__}
    out["dynslam"] = checkpoint.code_version()
    try:
        import numba

        out["numba"] = numba.__version__
        try:
            out["numba_threading_layer"] = numba.threading_layer()
        except ValueError:  # no parallel kernel has run yet: the layer asked for (utils/threads.py)
            out["numba_threading_layer"] = f"{numba.config.THREADING_LAYER} (requested)"
    except Exception:
        pass
    # the other libraries a trajectory depends on (ORB, the encoder, bundle adjustment), and the CPU:
    # float results, so trajectories, differ between builds and CPUs (README, "Reproducibility")
    for key, dists in LIBRARIES.items():
        for dist in dists:
            try:
                out[key] = importlib.metadata.version(dist)
                break
            except importlib.metadata.PackageNotFoundError:
                continue
    out["cpu"] = cpu_model()
    # how torch's OpenMP threads wait between parallel regions (utils/threads.passive_openmp): speed, not results
    out["omp_wait_policy"] = os.environ.get("OMP_WAIT_POLICY", "")
    if device is not None and device.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(device)
        out["cuda"] = torch.version.cuda
    return out


# run.json's versions: key -> the distributions that provide it (the first installed one is named)
LIBRARIES = {"opencv": ("opencv-python-headless", "opencv-python", "opencv-contrib-python-headless",
                        "opencv-contrib-python"),
             "onnxruntime": ("onnxruntime", "onnxruntime-gpu"), "openvino": ("openvino",), "gtsam": ("gtsam",),
             "scipy": ("scipy",)}


def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo; else platform.processor(); "unknown")."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def cpu_seconds() -> float:
    """The process's CPU time so far (s): user + system, every thread's."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def peak_rss_mb() -> float:
    """The process's peak resident memory so far (MiB): Linux's VmHWM (the kernel's high-water mark
    brought up to the resident set now; ru_maxrss alone can lag it by a few pages), else ru_maxrss
    (KiB on Linux, bytes on macOS)."""
    hwm = proc_status("VmHWM")
    if hwm is not None and hwm.isdigit():
        return int(hwm) / 1024.0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (2.0 ** 20 if sys.platform == "darwin" else 1024.0)
