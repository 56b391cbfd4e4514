"""motion/openvino_utils.py: an ONNX network on OpenVINO in fixed-shape batches."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch

from dynslam_cli.motion.openvino_utils import CHUNK, OvBatches

# found without importing it: a plain `import openvino` would start its telemetry in this process
pytestmark = pytest.mark.skipif(importlib.util.find_spec("openvino") is None,
                                reason="OpenVINO is not installed (pip install openvino)")


class _Net(torch.nn.Module):
    """Two outputs of different shapes, as EfficientNet's (features, logits)."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.conv = torch.nn.Conv2d(3, 8, 3, stride=2, padding=1)
        self.dw = torch.nn.Conv2d(8, 8, 5, padding=2, groups=8)
        self.fc = torch.nn.Linear(8, 5)

    def forward(self, x):
        f = torch.relu(self.dw(torch.relu(self.conv(x)))).mean((2, 3))
        return f, self.fc(f)


@pytest.fixture(scope="module")
def net_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("ov") / "net.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(_Net().eval(), (torch.zeros(2, 3, 24, 24),), str(path), input_names=["images"],
                          output_names=["features", "logits"], opset_version=17, dynamo=False,
                          dynamic_axes={"images": {0: "b"}, "features": {0: "b"}, "logits": {0: "b"}})
    return path


class TestOvBatches:
    @pytest.mark.parametrize("n", [1, CHUNK - 1, CHUNK, CHUNK + 1, 3 * CHUNK + 2])
    def test_any_batch_size_equals_the_network(self, net_path, n):
        x = np.random.default_rng(n).normal(size=(n, 3, 24, 24)).astype(np.float32)
        with torch.no_grad():
            f, lg = (t.numpy() for t in _Net().eval()(torch.from_numpy(x)))
        out = OvBatches(net_path, (3, 24, 24), ("features", "logits"), threads=1).run(x)
        assert [o.shape for o in out] == [(n, 8), (n, 5)] and all(o.dtype == np.float32 for o in out)
        assert np.allclose(out[0], f, atol=1e-5) and np.allclose(out[1], lg, atol=1e-5)

    def test_outputs_in_the_order_asked(self, net_path):
        x = np.random.default_rng(0).normal(size=(3, 3, 24, 24)).astype(np.float32)
        a = OvBatches(net_path, (3, 24, 24), ("features", "logits")).run(x)
        b = OvBatches(net_path, (3, 24, 24), ("logits", "features")).run(x)
        assert np.array_equal(a[0], b[1]) and np.array_equal(a[1], b[0])

    def test_a_row_does_not_depend_on_its_batch(self, net_path):
        x = np.random.default_rng(1).normal(size=(CHUNK + 1, 3, 24, 24)).astype(np.float32)
        ov = OvBatches(net_path, (3, 24, 24), ("features",), threads=1)
        whole = ov.run(x)[0]
        alone = np.concatenate([ov.run(x[i:i + 1])[0] for i in range(len(x))])
        assert np.allclose(whole, alone, atol=1e-6)

    def test_threads_at_once_get_what_each_gets_alone(self, net_path):
        # a run encodes the next frame in a worker thread while the loop encodes the rendered view (run/ahead.py):
        # one infer request would refuse the second call ("Infer Request is busy")
        from concurrent.futures import ThreadPoolExecutor

        rng = np.random.default_rng(2)
        xs = [rng.normal(size=(n, 3, 24, 24)).astype(np.float32) for n in (1, CHUNK, CHUNK + 3, 2 * CHUNK)] * 6
        ov = OvBatches(net_path, (3, 24, 24), ("features", "logits"), threads=1)
        alone = [ov.run(x) for x in xs]
        with ThreadPoolExecutor(4) as pool:
            together = list(pool.map(ov.run, xs))
        for a, b in zip(alone, together, strict=True):
            assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])

    def test_an_empty_batch_is_refused(self, net_path):
        with pytest.raises(ValueError, match="at least one image"):
            OvBatches(net_path, (3, 24, 24), ("features",)).run(np.zeros((0, 3, 24, 24), np.float32))


class TestImportOpenvino:
    def test_the_runtime_loads_without_the_telemetry(self, net_path, tmp_path):
        code = ("import sys, numpy as np\n"
                "from dynslam_cli.motion.openvino_utils import OvBatches\n"
                f"OvBatches({str(net_path)!r}, (3, 24, 24), ('features',), 1).run(np.zeros((1, 3, 24, 24), np.float32))\n"
                # no telemetry loaded, and no blocking entry left behind: a user's own import of the tools still works
                "print(sorted(m for m in sys.modules if 'telemetry' in m or m.startswith('openvino.tools.ovc')))\n")
        home = tmp_path / "home"
        home.mkdir()
        env = {**os.environ, "HOME": str(home)}
        env.pop("CI", None)  # OpenVINO turns its telemetry off on CI machines: test what a user's machine does
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == "[]" and not (home / "intel").exists()
