"""Segmenters: letterbox, NMS, YOLOv8-seg decoding (real model on the sample photos and synthetic
FastSAM-format outputs), part pruning, the weightless geometric segmenter."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.segment_base import masks_to_ids, prune_parts, relabel
from dynslam_cli.motion.segment_geometric import GeometricSegmenter
from dynslam_cli.motion.segment_yolo import YoloSegSegmenter, box_iou, decode, letterbox, nms
from dynslam_cli.motion.toyscene import render_toy, toy_intrinsics


def _read(path):
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


# ---------------------------------------------------------------- letterbox / NMS
def test_letterbox_keeps_aspect_and_pads_grey():
    img = np.full((100, 200, 3), 7, np.uint8)
    out, r, (left, top) = letterbox(img, (320, 320))
    assert out.shape == (320, 320, 3)
    assert r == pytest.approx(1.6)
    assert left == 0 and top == 80
    assert (out[:80] == 114).all() and (out[-80:] == 114).all()
    assert (out[80:240] == 7).all()
    # a point maps back: original = (letterboxed - pad) / r
    assert ((160 - left) / r, (160 - top) / r) == pytest.approx((100.0, 50.0))


def test_nms_class_aware_and_agnostic():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10], [50, 50, 60, 60]], np.float32)
    scores = np.array([0.9, 0.8, 0.7, 0.6], np.float32)
    classes = np.array([0, 0, 1, 0])
    assert box_iou(boxes[:1], boxes[1:2])[0, 0] == pytest.approx(81 / 119, rel=1e-4)
    assert list(nms(boxes, scores, 0.5, classes)) == [0, 2, 3]  # box 2 survives: another class
    assert list(nms(boxes, scores, 0.5, None)) == [0, 3]
    assert list(nms(boxes, scores, 0.9, None)) == [0, 1, 3]  # IoU 0.68 below 0.9 is kept


def test_decode_fastsam_format_synthetic():
    """A 1-class (FastSAM-format) output with two anchors on the same object and one elsewhere."""
    nm, mh, mw = 4, 16, 16
    protos = np.zeros((1, nm, mh, mw), np.float32)
    protos[0, 0] = -10.0
    protos[0, 0, 2:8, 2:8] = 10.0  # object 1 area in prototype space (input 64 → 4 px per cell)
    protos[0, 1] = -10.0
    protos[0, 1, 8:16, 9:15] = 10.0  # taller than its box (rows 40..56)
    anchors = np.zeros((4 + 1 + nm, 3), np.float32)
    anchors[:, 0] = [20, 20, 24, 24, 0.9, 1, 0, 0, 0]  # cx, cy, w, h, score, coeffs
    anchors[:, 1] = [21, 20, 24, 24, 0.6, 1, 0, 0, 0]  # duplicate, suppressed
    anchors[:, 2] = [48, 48, 24, 16, 0.8, 0, 1, 0, 0]
    boxes, scores, cls, masks = decode(anchors[None], protos, (64, 64), (64, 64), 1.0, (0, 0), conf=0.25, iou=0.7)
    assert len(boxes) == 2 and list(cls) == [0, 0]
    assert scores[0] == pytest.approx(0.9)
    assert masks.shape == (2, 64, 64)
    assert masks[0, 12:28, 12:28].all() and not masks[0, 40:, 40:].any()
    assert masks[1, 44:52, 40:56].all()
    assert not masks[1, :39].any() and not masks[1, 57:].any()  # cropped to its box
    assert not masks[1, :, :35].any()


# ---------------------------------------------------------------- pruning
def test_prune_parts_drops_contained_part_keeps_overlapping_neighbour():
    h = w = 40
    whole = np.zeros((h, w), bool)
    whole[5:35, 5:25] = True
    part = np.zeros((h, w), bool)
    part[6:15, 6:15] = True  # inside 'whole'
    neighbour = np.zeros((h, w), bool)
    neighbour[5:35, 20:38] = True  # overlaps 'whole' on 5 of its 18 columns
    masks = np.stack([part, whole, neighbour])
    kept = prune_parts(masks, 0.9, step=1)
    assert sorted(kept.tolist()) == [1, 2]
    # just below the threshold the part survives: 89% inside
    part2 = np.zeros((h, w), bool)
    part2[0:10, 5:15] = True  # rows 5..9 inside = 50%
    assert 0 in prune_parts(np.stack([part2, whole]), 0.9, step=1)
    ids, src = masks_to_ids(masks[kept])
    assert ids.max() == 2 and set(np.unique(ids)) == {0, 1, 2}
    # shared pixels go to the smaller segment (painted last)
    small = int(np.argmin([masks[kept][i].sum() for i in range(2)]))
    assert (ids[10:30, 21:24] == small + 1).all()


def test_masks_to_ids_min_area_and_relabel():
    m = np.zeros((3, 10, 10), bool)
    m[0, :5] = True
    m[1, 0, 0] = True  # 1 px, covered by m[0] anyway
    m[2, 8:, 8:] = True
    ids, src = masks_to_ids(m, min_area=2)
    assert ids.max() == 2 and list(src) == [0, 2]
    r, old = relabel(np.array([[0, 5, 5], [7, 7, 7]]), 1)
    assert r.tolist() == [[0, 1, 1], [2, 2, 2]] and old.tolist() == [5, 7]


# ---------------------------------------------------------------- YOLOv8-seg on real photos
def test_yolo_seg_bus(yolo_model, shared_dir):
    seg_model = YoloSegSegmenter(str(yolo_model))
    assert seg_model.input_hw == (320, 320)  # read from the model
    img = _read(shared_dir / "images" / "bus.jpg")
    boxes, scores, cls, masks = seg_model.detect(img)
    names = [seg_model.names[int(c)] for c in cls]
    assert names.count("person") >= 3 and "bus" in names
    seg = seg_model.segment(img)
    assert seg.ids.shape == img.shape[:2] and seg.ids.dtype == np.int32
    assert seg.count == len(seg.class_ids) == len(seg.scores) == int(seg.ids.max())
    bus_id = int(np.nonzero(seg.class_ids == 5)[0][0]) + 1
    bus = seg.ids == bus_id
    # the bus covers much of the middle band of the photo, not the sky/road at the top/bottom
    assert 0.2 < bus.mean() < 0.45
    assert bus[400:600, 300:700].mean() > 0.8 and not bus[:150].any()
    for k in np.nonzero(seg.class_ids == 0)[0]:
        m = seg.ids == k + 1
        ys, xs = np.nonzero(m)
        assert (ys.max() - ys.min()) > 1.5 * (xs.max() - xs.min())  # upright people
        assert 0.005 < m.mean() < 0.1


def test_yolo_seg_zidane(yolo_model, shared_dir):
    seg = YoloSegSegmenter(str(yolo_model)).segment(_read(shared_dir / "images" / "zidane.jpg"))
    assert (seg.class_ids == 0).sum() >= 2
    areas = [(seg.ids == k + 1).mean() for k in np.nonzero(seg.class_ids == 0)[0]]
    assert all(0.1 < a < 0.4 for a in areas[:2])


def test_yolo_seg_missing_model_message(tmp_path):
    with pytest.raises(DynslamError, match=r"model file not found: .*nope\.onnx.*export"):
        YoloSegSegmenter(str(tmp_path / "nope.onnx"))
    with pytest.raises(DynslamError, match="no model file configured"):
        YoloSegSegmenter("")


# ---------------------------------------------------------------- ONNX models of the wrong kind
def _onnx(path, outputs, inp=("images", [1, 3, 32, 32])):
    """A tiny ONNX model: one float input and constant float outputs ``name: (shape, declared)``
    (``declared`` None = the shape itself; strings in it are symbolic dimensions)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    nodes, outs = [], []
    for name, (shape, declared) in outputs.items():
        value = numpy_helper.from_array(np.zeros(shape, np.float32), name=f"{name}_value")
        nodes.append(helper.make_node("Constant", [], [name], value=value))
        outs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, shape if declared is None else declared))
    x = helper.make_tensor_value_info(inp[0], TensorProto.FLOAT, inp[1])
    model = helper.make_model(helper.make_graph(nodes, "wrong", [x], outs),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


@pytest.mark.parametrize("outputs, inp, why", [
    ({"logits": ([1, 10], None)}, None, "1 output, not 2"),  # an image classifier
    ({"output0": ([1, 37, 16], None), "output1": ([1, 32, 8], None)}, None, "rank 3 and 3"),
    ({"output0": ([1, 36, 16], None), "output1": ([1, 32, 8, 8], None)}, None, "output0 has 36 channels"),
    ({"output0": ([1, 37, 16], None), "output1": ([1, 32, 8, 8], None)}, ("x", [1, 32]), "input"),
])
def test_yolo_seg_wrong_model_kind(tmp_path, outputs, inp, why):
    path = _onnx(tmp_path / "wrong.onnx", outputs, inp or ("images", [1, 3, 32, 32]))
    with pytest.raises(DynslamError) as info:
        YoloSegSegmenter(str(path))
    msg = str(info.value)
    assert str(path) in msg and why in msg and "\n" not in msg, msg
    assert "output0 1×(4+C+32)×N" in msg and "output1 1×32×H×W" in msg
    assert next(iter(outputs)) in msg  # what the model has


def _onnx_symbolic(path):
    """A model whose output0 has a symbolic channel count: 1×W×16 for a 1×3×H×W input (W = imgsz)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    def const(name, arr):
        return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(arr, name=f"{name}_v"))

    nodes = [
        helper.make_node("Shape", ["images"], ["shape"]),
        const("s3", np.array([3], np.int64)), const("s4", np.array([4], np.int64)),
        helper.make_node("Slice", ["shape", "s3", "s4"], ["w"]),
        const("one", np.array([1], np.int64)),
        helper.make_node("Concat", ["one", "w", "one"], ["reps"], axis=0),
        const("row", np.zeros((1, 1, 16), np.float32)),
        helper.make_node("Tile", ["row", "reps"], ["output0"]),
        const("output1", np.zeros((1, 32, 8, 8), np.float32)),
    ]
    x = helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, "h", "w"])
    outs = [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, "c", "n"]),
            helper.make_tensor_value_info("output1", TensorProto.FLOAT, [1, 32, 8, 8])]
    model = helper.make_model(helper.make_graph(nodes, "symbolic", [x], outs),
                              opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path


def test_yolo_seg_symbolic_shapes_checked_on_the_first_frame(tmp_path):
    # output0's channel count is symbolic, so the model loads; the arrays it returns are checked on a frame
    path = _onnx_symbolic(tmp_path / "dyn.onnx")
    seg = YoloSegSegmenter(str(path), imgsz=20)
    with pytest.raises(DynslamError, match=r"dyn\.onnx returned arrays 1×20×16 and 1×32×8×8; expected YOLOv8-seg"):
        seg.segment(np.zeros((24, 32, 3), np.uint8))
    # 4 + 1 class + 32 coefficients: no detection above the threshold, an empty segmentation
    assert YoloSegSegmenter(str(path), imgsz=37).segment(np.zeros((24, 32, 3), np.uint8)).ids.max() == 0


def test_onnx_encoder_wrong_model_kind(tmp_path):
    from dynslam_cli.motion.encode_onnx import OnnxEncoder

    path = _onnx(tmp_path / "vec.onnx", {"v": ([7], None)}, ("images", [1, 3, 32, 32]))
    with pytest.raises(DynslamError, match=r"vec\.onnx output 'v' has rank 1; it has inputs images\[1×3×32×32\]"):
        OnnxEncoder(str(path), input_size=32)
    path = _onnx(tmp_path / "text.onnx", {"e": ([1, 8], None)}, ("tokens", [1, 77]))
    with pytest.raises(DynslamError, match=r"text\.onnx is not a model of the expected kind.*tokens\[1×77\].*N×3×S×S"):
        OnnxEncoder(str(path))


# ---------------------------------------------------------------- geometric
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_geometric_person_in_front_of_wall(seed):
    rgb, depth, gt = render_toy(320, 240, person_x=-0.3 + 0.1 * seed, noise=0.003, seed=seed)
    seg = GeometricSegmenter(intrinsics=toy_intrinsics(320, 240)).segment(rgb, depth)
    person = gt == 1
    vals, counts = np.unique(seg.ids[person], return_counts=True)
    k = vals[counts.argmax()]
    inst = seg.ids == k
    assert k != 0
    assert counts.max() / person.sum() > 0.9  # one instance covers the person (shirt + trousers + head)
    assert (inst & person).sum() / inst.sum() > 0.9  # and holds little of the wall/floor
    # the wall and the floor are segments of their own, not merged into the person
    floor = (gt == 0) & (depth < 3.4)
    wall = (gt == 0) & (depth >= 3.49)
    wall_id = np.bincount(seg.ids[wall]).argmax()
    assert wall_id not in (0, k)
    box = gt == 2
    assert np.bincount(seg.ids[box]).argmax() not in (0, k, wall_id)
    assert np.bincount(seg.ids[floor], minlength=k + 1)[k] < 0.05 * floor.sum()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_geometric_extent_follows_depth(seed):
    rgb, depth, gt = render_toy(320, 240, person_x=-0.3 + 0.1 * seed, noise=0.003, seed=seed)
    seg = GeometricSegmenter(intrinsics=toy_intrinsics(320, 240)).segment(rgb, depth)
    assert seg.extent.shape == seg.ids.shape and seg.extent.dtype == np.int32
    assert seg.extent.max() == seg.ids.max()  # the same instances, numbered alike
    labelled = seg.ids > 0
    assert (seg.extent[labelled] == seg.ids[labelled]).mean() > 0.97  # they differ on the edge bands only
    person = gt == 1
    k = np.bincount(seg.ids[person]).argmax()
    ext, own = seg.extent == k, seg.ids == k
    # the edge band beside the depth step joins the side at its depth: the person's extent holds none of
    # the wall (its id's pixels, the band given to the nearest segment, 0.5-0.8 %)
    assert (ext & person).sum() / ext.sum() > 0.999
    assert (own & person).sum() / own.sum() < (ext & person).sum() / ext.sum()
    assert (ext & person).sum() >= (own & person).sum()


def test_geometric_speed_320x240():
    rgb, depth, _ = render_toy(320, 240, noise=0.003)
    s = GeometricSegmenter()
    s.segment(rgb, depth)
    times = []
    for _ in range(3):
        t = time.perf_counter()
        s.segment(rgb, depth)
        times.append(time.perf_counter() - t)
    assert min(times) < 0.1  # ~5 ms on one core; generous for a loaded machine


def test_geometric_fills_sensor_holes_with_the_surrounding_segment():
    rgb, depth, gt = render_toy(320, 240, noise=0.003)
    holes = np.random.default_rng(0).random(depth.shape) < 0.01  # 1 % isolated pixels without depth
    depth[holes] = 0
    seg = GeometricSegmenter(intrinsics=toy_intrinsics(320, 240)).segment(rgb, depth)
    person = gt == 1
    k = np.bincount(seg.ids[person & ~holes]).argmax()
    # the person's holes belong to the person (the motion mask has no pinholes), not to 'no segment'
    assert (seg.ids[person & holes] == k).mean() > 0.9
    assert (seg.ids[holes] == 0).mean() < 0.05


def test_geometric_handles_holes_and_no_rgb():
    rgb, depth, gt = render_toy(160, 120)
    depth[:, :40] = 0  # a band without depth
    seg = GeometricSegmenter().segment(None, depth)
    assert (seg.ids[:, :30] == 0).all()
    assert seg.count >= 2
