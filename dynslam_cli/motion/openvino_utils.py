"""OpenVINO inference of an image network on the CPU, in batches of fixed shape.

On the CPU, OpenVINO runs EfficientNet-Lite0's depthwise convolutions about 2.5 times as fast as
onnxruntime (docs/experiments.md, "The encoder on OpenVINO"), with embeddings within 1e-6 of its. Every
new input shape costs OpenVINO a compilation (0.1-0.5 s), and the number of crops changes from
frame to frame, so the network is compiled once for a batch of :data:`CHUNK` images and once for a
single image: a batch of n images runs as n // CHUNK full chunks and n % CHUNK single images
(the cost per image is flat from a batch of 2 upwards).
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

CHUNK = 4
# imported by ``import openvino`` unless blocked; it starts OpenVINO's usage telemetry (below)
_CONVERSION_TOOLS = "openvino.tools.ovc"


def import_openvino():
    """``import openvino`` without its model-conversion tools (``openvino.tools.ovc``, which the package imports
    only if it can). Importing those starts OpenVINO's usage telemetry: a client id written under ``~/intel`` and
    an event sent to Google Analytics on every import unless the user opted out. A SLAM run needs only the runtime
    and has no business sending anything; a user's own later ``import openvino.tools.ovc`` still works."""
    import sys

    blocked = _CONVERSION_TOOLS not in sys.modules
    if blocked:
        sys.modules[_CONVERSION_TOOLS] = None
    try:
        import openvino
    finally:
        if blocked and sys.modules.get(_CONVERSION_TOOLS, 0) is None:
            del sys.modules[_CONVERSION_TOOLS]
    return openvino


class OvBatches:
    """An ONNX network with one N×C×H×W float input, compiled for CPU batches of ``chunk`` and of 1
    image; :meth:`run` takes any batch size and returns the outputs ``outputs`` in that order.

    ``threads`` 0 = OpenVINO's default (every core). Precision is fp32 even on CPUs where OpenVINO
    would default to bf16, so the outputs are the network's."""

    def __init__(self, path: str | Path, image_chw: tuple[int, int, int], outputs: tuple[str, ...], threads: int = 0,
                 chunk: int = CHUNK):
        ov = import_openvino()
        core = ov.Core()
        cfg = {"PERFORMANCE_HINT": "LATENCY", "INFERENCE_PRECISION_HINT": "f32"}
        if threads > 0:
            cfg["INFERENCE_NUM_THREADS"] = int(threads)
        self.chunk = max(1, int(chunk))
        self.outputs = tuple(outputs)
        self.compiled = {}
        for b in sorted({self.chunk, 1}):
            model = core.read_model(str(path))
            model.reshape({model.inputs[0].get_any_name(): [b, *image_chw]})
            self.compiled[b] = core.compile_model(model, "CPU", cfg)
        # an infer request serves one call at a time: each thread gets its own (a run encodes the next frame's
        # segments in a worker thread while the loop encodes the rendered view's, run/ahead.py)
        self._local = threading.local()

    def _request(self, b: int):
        reqs = self._local.__dict__.setdefault("requests", {})
        if b not in reqs:
            reqs[b] = self.compiled[b].create_infer_request()
        return reqs[b]

    def _infer(self, x: np.ndarray) -> list[np.ndarray]:
        res = self._request(len(x)).infer({0: np.ascontiguousarray(x, np.float32)})
        by_name = {k.get_any_name(): v for k, v in res.items()}
        return [np.array(by_name[n], np.float32, copy=True) for n in self.outputs]

    def run(self, x: np.ndarray) -> list[np.ndarray]:
        n = len(x)
        if n == 0:
            raise ValueError("OvBatches.run needs at least one image")
        full = n - n % self.chunk
        parts = [self._infer(x[i:i + self.chunk]) for i in range(0, full, self.chunk)]
        parts += [self._infer(x[i:i + 1]) for i in range(full, n)]
        return [np.concatenate([p[k] for p in parts]) for k in range(len(self.outputs))]
