"""Encoders: masked crops, EfficientNet-Lite0 (real ImageNet weights), the generic ONNX path with
tiny models exported here, presets' missing-file messages, the colour histogram."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.encode_base import instance_boxes, masked_crops, normalise_batch
from dynslam_cli.motion.encode_hist import ColorHistEncoder
from dynslam_cli.motion.encode_onnx import OnnxEncoder, pool

torch = pytest.importorskip("torch")


def _read(path):
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def _two_instances(h=60, w=80):
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[:] = (0, 0, 255)
    ids = np.zeros((h, w), np.int32)
    ids[10:30, 5:25] = 1
    rgb[10:30, 5:25] = (255, 0, 0)
    ids[35:55, 40:75] = 2
    rgb[35:55, 40:75] = (0, 255, 0)
    return rgb, ids


# ---------------------------------------------------------------- crops
def test_instance_boxes_and_masked_crops():
    rgb, ids = _two_instances()
    boxes = instance_boxes(ids, 2)
    assert boxes.tolist() == [[5, 10, 25, 30], [40, 35, 75, 55]]
    crops = masked_crops(rgb, ids, 32, margin=0.1, fill=(9, 9, 9))
    assert crops.shape == (2, 32, 32, 3) and crops.dtype == np.uint8
    assert tuple(crops[0, 16, 16]) == (255, 0, 0)
    assert tuple(crops[0, 0, 0]) == (9, 9, 9)  # background greyed, not the blue image
    assert not (crops == (0, 0, 255)).all(-1).any()
    assert tuple(crops[1, 16, 16]) == (0, 255, 0)
    # stacked masks give the same crops as the id map
    masks = np.stack([ids == 1, ids == 2])
    assert np.array_equal(masked_crops(rgb, masks, 32, 0.1, (9, 9, 9)), crops)


def test_instance_boxes_of_absent_ids_are_zero():
    _, ids = _two_instances()
    ids[ids == 1] = 0  # id 1 absent, id 3 beyond the map
    assert instance_boxes(ids, 3).tolist() == [[0, 0, 0, 0], [40, 35, 75, 55], [0, 0, 0, 0]]
    assert instance_boxes(ids, 0).shape == (0, 4)


def test_normalise_batch_is_the_formula_bit_for_bit():
    crops = np.random.default_rng(0).integers(0, 256, (3, 8, 6, 3), dtype=np.uint8)
    mean, std = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
    x = (crops.astype(np.float32) / 255.0 - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    out = normalise_batch(crops, mean, std)
    assert out.shape == (3, 3, 8, 6) and out.dtype == np.float32 and out.flags.c_contiguous
    assert np.array_equal(out, x.transpose(0, 3, 1, 2))


# ---------------------------------------------------------------- EfficientNet-Lite0
BUS_LIKE = {654, 779, 874, 705, 734, 675}  # minibus, school bus, trolleybus, passenger car, police van, moving van
SUIT_LIKE = {834, 906, 457, 819, 768}  # suit, Windsor tie, bow tie, stage, rugby ball


@pytest.fixture(scope="module")
def effnet_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def effnet(effnet_cache):
    from dynslam_cli.motion.encode_effnet import EffNetLite0Encoder

    try:
        return EffNetLite0Encoder(backend="auto", cache=effnet_cache)
    except DynslamError as exc:
        pytest.skip(str(exc))


def test_effnet_classifies_sample_photos(effnet, shared_dir):
    assert effnet.backend == "openvino"
    top = effnet.classify(_read(shared_dir / "images" / "bus.jpg"))
    assert top[0][0] in BUS_LIKE and top[0][1] > 0.5
    top = effnet.classify(_read(shared_dir / "images" / "zidane.jpg"))
    assert {i for i, _ in top} & {834, 906, 457}


def test_effnet_torch_onnxruntime_and_openvino_agree_and_embed(effnet, effnet_cache):
    from dynslam_cli.motion.encode_effnet import EffNetLite0Encoder

    rgb, ids = _two_instances(120, 160)
    e1 = effnet.encode(rgb, ids)
    assert e1.shape == (2, 1280) and e1.dtype == np.float32
    assert np.allclose(np.linalg.norm(e1, axis=1), 1.0, atol=1e-5)
    e2 = EffNetLite0Encoder(backend="torch").encode(rgb, ids)
    assert np.abs(e1 - e2).max() < 1e-3
    ort = EffNetLite0Encoder(backend="onnx", cache=effnet_cache)
    assert ort.backend == "onnxruntime" and np.abs(e1 - ort.encode(rgb, ids)).max() < 1e-5
    assert effnet.encode(rgb, np.zeros_like(ids)).shape == (0, 1280)
    # the red and the green square are different things
    assert float(e1[0] @ e1[1]) < 0.95


def test_effnet_runs_at_a_smaller_input_size(shared_dir, tmp_path, monkeypatch):
    from dynslam_cli.config import Config
    from dynslam_cli.motion.encoders import make_encoder

    monkeypatch.setenv("DYNSLAM_CACHE", str(tmp_path))
    cfg = Config()
    assert cfg.motion.encoder_input_size == 0  # effnet-lite0's own size: 160
    small = make_encoder(cfg.motion, threads=1)
    assert small.input_size == 160
    assert (tmp_path / "effnet-lite0-160-v1.onnx").is_file() and small.backend == "openvino"
    top = small.classify(_read(shared_dir / "images" / "bus.jpg"))
    assert top[0][0] in BUS_LIKE
    rgb, ids = _two_instances(120, 160)
    e = small.encode(rgb, ids)
    assert e.shape == (2, 1280) and np.allclose(np.linalg.norm(e, axis=1), 1.0, atol=1e-5)
    with pytest.raises(DynslamError, match="encoder_input_size"):
        type(small)(input_size=16)


def test_effnet_embedding_separates_people_from_bus(effnet, yolo_model, shared_dir):
    from dynslam_cli.motion.segment_yolo import YoloSegSegmenter

    img = _read(shared_dir / "images" / "bus.jpg")
    seg = YoloSegSegmenter(str(yolo_model)).segment(img)
    emb = effnet.encode(img, seg.ids)
    people = emb[seg.class_ids == 0]
    bus = emb[seg.class_ids == 5]
    pp = people @ people.T
    within = pp[np.triu_indices(len(people), 1)].mean()
    across = (people @ bus.T).mean()
    assert within > across


# ---------------------------------------------------------------- generic ONNX path
class _MapNet(torch.nn.Module):
    """Tiny conv net: output 0 a feature map B×8×h×w, output 1 tokens B×T×8."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.conv = torch.nn.Conv2d(3, 8, 3, stride=4, padding=1)

    def forward(self, x):
        f = torch.relu(self.conv(x))
        return f, f.flatten(2).transpose(1, 2)


def _export(path, size=32, dynamic=True):
    kw = {"dynamic_axes": {"images": {0: "b"}, "fmap": {0: "b"}, "tokens": {0: "b"}}} if dynamic else {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(_MapNet().eval(), (torch.zeros(1, 3, size, size),), str(path), input_names=["images"],
                          output_names=["fmap", "tokens"], opset_version=17, dynamo=False, **kw)
    return path


def test_onnx_encoder_feature_map_and_tokens(tmp_path):
    path = _export(tmp_path / "tiny.onnx", 32)
    rgb, ids = _two_instances()
    enc = OnnxEncoder(str(path))
    assert enc.size == 32 and enc.dim == 8  # input size read from the model
    z = enc.encode(rgb, ids)
    assert z.shape == (2, 8) and np.allclose(np.linalg.norm(z, axis=1), 1, atol=1e-5)
    # by hand: crop, normalise, run, mean over space
    import onnxruntime as ort

    crops = masked_crops(rgb, ids, 32, 0.1, enc.fill)
    x = ((crops / 255.0 - np.array([0.485, 0.456, 0.406])) / np.array([0.229, 0.224, 0.225])).transpose(0, 3, 1, 2)
    ref = ort.InferenceSession(str(path)).run(["fmap"], {"images": x.astype(np.float32)})[0].mean((2, 3))
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    assert np.allclose(z, ref, atol=1e-5)
    # the token output (by index), mean-pooled, is the same numbers
    zt = OnnxEncoder(str(path), output="1").encode(rgb, ids)
    assert np.allclose(zt, z, atol=1e-5)
    assert not np.allclose(OnnxEncoder(str(path), output="tokens", pooling="cls").encode(rgb, ids), z)
    # mean/std matter
    assert not np.allclose(OnnxEncoder(str(path), mean=[0.5] * 3, std=[0.5] * 3).encode(rgb, ids), z)


def test_onnx_encoder_fixed_batch_one(tmp_path):
    path = _export(tmp_path / "fixed.onnx", 32, dynamic=False)
    rgb, ids = _two_instances()
    enc = OnnxEncoder(str(path))
    assert enc.fixed_batch == 1
    z = enc.encode(rgb, ids)
    assert z.shape == (2, 8)
    assert np.allclose(z, OnnxEncoder(str(_export(tmp_path / "dyn.onnx", 32))).encode(rgb, ids), atol=1e-5)


def test_onnx_sessions_stay_on_the_cpu_for_a_cpu_run(tmp_path, monkeypatch):
    import onnxruntime as ort

    from dynslam_cli.motion.onnx_utils import ort_session

    path = _export(tmp_path / "tiny.onnx", 32)
    assert ort_session(path, 1, "cpu").get_providers() == ["CPUExecutionProvider"]
    # a CUDA run asks for onnxruntime's CUDA provider first, where this onnxruntime has one
    asked = []

    class Session:
        def __init__(self, path, sess_options=None, providers=None):
            asked.append(providers)

    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    monkeypatch.setattr(ort, "InferenceSession", Session)
    ort_session(path, 1, "cuda")
    ort_session(path, 1, "cpu")
    assert asked == [["CUDAExecutionProvider", "CPUExecutionProvider"], ["CPUExecutionProvider"]]


def test_effnet_on_a_cuda_run_is_the_torch_network(monkeypatch):
    from dynslam_cli.motion import encode_effnet

    moved = []
    monkeypatch.setattr(torch.nn.Module, "to", lambda self, device: moved.append(device) or self)
    enc = encode_effnet.EffNetLite0Encoder(device="cuda")
    assert enc.backend == "torch" and enc.session is None and enc.ov is None and moved == ["cuda"]


def test_effnet_backend_falls_back_and_names_its_runtime(monkeypatch, tmp_path):
    import sys

    from dynslam_cli.motion.encode_effnet import EffNetLite0Encoder

    with pytest.raises(DynslamError, match="unknown EfficientNet backend 'tensorrt'"):
        EffNetLite0Encoder(backend="tensorrt")
    monkeypatch.setitem(sys.modules, "openvino", None)  # OpenVINO not installed
    enc = EffNetLite0Encoder(backend="auto", cache=tmp_path)
    assert enc.backend == "onnxruntime" and enc.ov is None and enc.session is not None
    with pytest.raises(ImportError):
        EffNetLite0Encoder(backend="openvino", cache=tmp_path)


def test_onnx_encoder_errors(tmp_path):
    with pytest.raises(DynslamError, match=r"clip encoder.*not found: .*missing\.onnx.*open_clip"):
        OnnxEncoder(str(tmp_path / "missing.onnx"), preset="clip")
    with pytest.raises(DynslamError, match=r"dino.*dinov2_vits14\.onnx.*torch\.hub"):
        OnnxEncoder("", preset="dino")
    with pytest.raises(DynslamError, match=r"blip.*Blip2Model"):
        OnnxEncoder("", preset="blip")
    path = _export(tmp_path / "tiny.onnx", 32)
    with pytest.raises(DynslamError, match="no output 'nope'.*fmap, tokens"):
        OnnxEncoder(str(path), output="nope")
    with pytest.raises(DynslamError, match="takes 32×32"):
        OnnxEncoder(str(path), input_size=64)
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(DynslamError, match="cannot load ONNX model"):
        OnnxEncoder(str(bad))


def test_pool_shapes():
    assert pool(np.ones((2, 5))).shape == (2, 5)
    t = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    assert np.allclose(pool(t, "cls"), t[:, 0]) and np.allclose(pool(t, "mean"), t.mean(1))
    assert pool(np.ones((2, 4, 3, 3))).shape == (2, 4)
    with pytest.raises(DynslamError):
        pool(np.ones(3))


def test_make_encoder_presets_from_config(tmp_path):
    from dynslam_cli.config import Config
    from dynslam_cli.motion.encoders import make_encoder

    cfg = Config()
    cfg.motion.encoder = "clip"
    with pytest.raises(DynslamError, match="clip encoder"):
        make_encoder(cfg.motion)
    cfg.motion.encoder = "onnx"
    cfg.motion.encoder_model = str(_export(tmp_path / "t.onnx", 32))
    assert make_encoder(cfg.motion).dim == 8
    cfg.motion.encoder = "nope"
    with pytest.raises(DynslamError, match="unknown motion.encoder"):
        make_encoder(cfg.motion)


# ---------------------------------------------------------------- colour histogram
def test_color_hist():
    rgb, ids = _two_instances()
    enc = ColorHistEncoder()
    z = enc.encode(rgb, ids)
    assert z.shape == (2, enc.dim) and np.allclose(np.linalg.norm(z, axis=1), 1)
    assert float(z[0] @ z[1]) < 0.01  # pure red vs pure green: disjoint bins
    rgb2 = rgb.copy()
    rgb2[35:55, 40:75] = (250, 5, 5)  # instance 2 now red too
    z2 = enc.encode(rgb2, ids)
    assert float(z2[0] @ z2[1]) > 0.99
    assert np.allclose(enc.encode(rgb, np.stack([ids == 1, ids == 2])), z)
