"""The inconsistency check (both directions) and the MotionModule end to end on toy frames."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dynslam_cli.config import Config
from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.check import inconsistency_check
from dynslam_cli.motion.segment_geometric import GeometricSegmenter
from dynslam_cli.motion.toyscene import render_toy, toy_intrinsics
from dynslam_cli.slam.keyframes import subsample_depth

torch = pytest.importorskip("torch")


# ---------------------------------------------------------------- check
def _planes(h=60, w=80):
    ids = np.zeros((h, w), np.int32)
    ids[10:40, 10:30] = 1
    ids[10:40, 45:70] = 2
    return ids


def test_check_forward_flags_what_stands_in_front():
    ids = _planes()
    rendered = np.full(ids.shape, 2.5, np.float32)
    observed = rendered.copy()
    observed[ids == 1] = 2.0  # 0.5 m in front of the map
    res = inconsistency_check(observed, rendered, ids, 0.3, 0.05, width=80)
    assert res.forward.tolist() == [True, False] and res.observed_moving.tolist() == [True, False]
    assert res.fractions[0] == pytest.approx(1.0) and res.fractions[1] == 0
    assert not res.background_moving
    # 0.2 m is under t_d
    observed[ids == 1] = 2.3
    assert not inconsistency_check(observed, rendered, ids, 0.3, 0.05, width=80).forward.any()
    # t_p: 3% of the pixels in front is not enough, 10% is
    observed = rendered.copy()
    ys, xs = np.nonzero(ids == 2)
    n = len(ys)
    observed[ys[: int(0.03 * n)], xs[: int(0.03 * n)]] = 1.0
    assert not inconsistency_check(observed, rendered, ids, 0.3, 0.05, width=80).forward[1]
    observed[ys[: int(0.10 * n)], xs[: int(0.10 * n)]] = 1.0
    assert inconsistency_check(observed, rendered, ids, 0.3, 0.05, width=80).forward[1]
    # invalid depth is not evidence; a rendered map at another resolution is resized inside
    observed[ids == 2] = 0
    res = inconsistency_check(observed, rendered[::2, ::2], ids, 0.3, 0.05, width=80)
    assert not res.forward[1] and not res.judged[1]


def test_check_reverse_flags_what_left_or_moved_away():
    ids = _planes()
    rendered = np.full(ids.shape, 3.0, np.float32)
    rendered[10:40, 10:30] = 2.5  # the map still has an object here ...
    observed = np.full(ids.shape, 3.0, np.float32)
    observed[10:40, 10:30] = 3.0  # ... the camera now sees the wall 0.5 m behind it
    rrgb = np.full(ids.shape + (3,), 200, np.uint8)
    rrgb[10:40, 10:30] = (30, 160, 40)
    seg = GeometricSegmenter(width=80, min_area=0.01, min_instance_area=4)
    res = inconsistency_check(observed, rendered, ids, 0.3, 0.05, rendered_rgb=rrgb, rendered_segmenter=seg,
                              width=80, backward_current=True)
    assert not res.forward.any()
    assert res.backward.tolist() == [True, False] and res.observed_moving.tolist() == [True, False]
    # by default the uncovered wall is not labelled moving: only the rendered segment is flagged
    dflt = inconsistency_check(observed, rendered, ids, 0.3, 0.05, rendered_rgb=rrgb, rendered_segmenter=seg,
                               width=80)
    assert not dflt.observed_moving.any() and dflt.rendered_flagged.tolist() == res.rendered_flagged.tolist()
    assert len(res.rendered_flagged) == 1
    flagged = res.rendered_ids == res.rendered_flagged[0]
    assert flagged[12:38, 12:28].all() and not flagged[:, 40:].any()
    # without the rendered-view segmentation only the forward direction runs
    res = inconsistency_check(observed, rendered, ids, 0.3, 0.05, width=80)
    assert not res.observed_moving.any()


def test_check_background_is_checked():
    ids = _planes()
    rendered = np.full(ids.shape, 2.5, np.float32)
    observed = rendered.copy()
    observed[ids == 0] = 1.5
    res = inconsistency_check(observed, rendered, ids, 0.3, 0.05, width=80)
    assert res.background_moving and res.background_forward > 0.9 and not res.observed_moving.any()


# ---------------------------------------------------------------- module
W, H = 160, 120


def _frame(index, **kw):
    rgb, depth, gt = render_toy(W, H, seed=index, **kw)
    return SimpleNamespace(index=index, timestamp=index / 30, rgb=rgb, depth=depth, gt=gt, pose_c2w=np.eye(4))


def _module(encoder="color-hist", **over):
    from dynslam_cli.motion.module import MotionModule

    cfg = Config()
    cfg.motion.encoder = encoder
    for k, v in over.items():
        setattr(cfg.motion, k, v)
    mod = MotionModule(cfg, toy_intrinsics(W, H), torch.device("cpu"))
    mod.segmenter.min_instance_area = 16  # the toy frames are small
    return mod


def _instance_of(inst, mask):
    vals, counts = np.unique(inst.ids[mask], return_counts=True)
    return int(vals[counts.argmax()])


def test_module_end_to_end_person_learned_and_keyframes_forget():
    mod = _module()
    pose = np.eye(4)
    f0 = _frame(0, person_x=-0.3)
    # the map (rendered) and the last keyframe saw the empty room: the person stands 1.5 m in front of it
    room_depth = render_toy(W, H, person=False)[1]
    room_kf = SimpleNamespace(pose_c2w=pose, depth_raw_small=subsample_depth(room_depth))
    inst0 = mod.observe(f0, pose)
    assert inst0.extent is None and inst0.grown is not None  # the outline waits for the tracked pose
    assert inst0.count >= 3 and inst0.embeddings.shape == (inst0.count, mod.encoder.dim)
    assert not inst0.dynamic.any() and inst0.static_mask.all()
    assert {"segment", "encode", "classify"} <= set(inst0.timings)
    pid = _instance_of(inst0, f0.gt == 1)
    assert np.isfinite(inst0.centres[pid - 1]).all()
    assert inst0.centres[pid - 1][2] == pytest.approx(2.0, abs=0.3)  # the person stands 2 m away
    kept0 = mod.keyframe_instances(inst0)  # what a keyframe keeps to re-classify its instances
    assert kept0[0].shape[0] == inst0.count and kept0[1].dtype == bool
    assert mod.dynamic_ids(*kept0).size == 0
    rec = mod.check_and_update(f0, inst0, pose, room_depth[::2, ::2], None)
    assert rec is not None and rec.frame == 0
    assert rec.loss_after < rec.loss_before and rec.fixed and rec.replay_size >= 1
    assert inst0.dynamic[pid - 1] and inst0.dynamic.sum() == 1
    assert not inst0.static_mask[f0.gt == 1].mean() > 0.1
    assert inst0.static_mask[f0.gt == 0].mean() > 0.9
    # at the tracked pose: no keyframe says where something new stands: the ids mask
    np.testing.assert_array_equal(mod.bound_outline(inst0, f0.depth, pose, [], inst0.static_mask, inst0.dynamic),
                                  inst0.static_mask)
    assert inst0.extent is None
    # what is masked (and written as the frame's motion mask) is the person's extent where the keyframe saw the
    # room: its outline band too, not only its id's pixels; no wall pixel the keyframe saw as wall
    for_map = mod.bound_outline(inst0, f0.depth, pose, [room_kf], inst0.static_mask, inst0.dynamic)
    assert not for_map[inst0.extent == pid].any() and (for_map <= inst0.static_mask).all()
    none = np.zeros_like(inst0.dynamic)
    np.testing.assert_array_equal(mod.bound_outline(inst0, f0.depth, pose, [room_kf], mod._static_mask(inst0.ids, none),
                                                    none), np.ones_like(for_map))  # nothing dynamic: everything usable
    assert inst0.extent is not None and (inst0.mask_ids == inst0.extent).all()
    np.testing.assert_array_equal(inst0.dynamic_mask(), inst0.extent == pid)
    assert (inst0.extent == pid).sum() > (inst0.ids == pid).sum()
    assert (f0.gt[inst0.extent == pid] == 1).mean() > (f0.gt[inst0.ids == pid] == 1).mean()
    # the keyframe stored before the update now forgets the person's rays
    assert mod.dynamic_ids(*kept0).tolist() == [pid]
    # next frame: the person moved; g already calls it dynamic, the check agrees → no update
    f1 = _frame(1, person_x=0.2)
    inst1 = mod.observe(f1, pose)
    pid1 = _instance_of(inst1, f1.gt == 1)
    assert inst1.dynamic[pid1 - 1] and inst1.dynamic.sum() == 1
    assert mod.check_and_update(f1, inst1, pose, room_depth, None) is None
    assert mod.updates == 1
    # told the person has stood still (stationary), the check labels it static despite the map
    # (without the centre feature the replayed person keeps g from flipping it: not asserted)
    stationary = np.zeros(inst1.count, bool)
    stationary[pid1 - 1] = True
    rec_still = mod.check_and_update(f1, inst1, pose, room_depth, None, None, stationary)
    assert rec_still is not None and not any(rec_still.labels) and mod.updates == 2
    json_line = rec.to_json()
    assert set(json_line) >= {"frame", "instances", "labels", "loss_before", "loss_after", "replay_size"}
    import json

    assert json.loads(json.dumps(json_line))["labels"] == rec.labels  # one line of classifier_updates.jsonl


def test_module_bidirectional_object_that_left():
    mod = _module()
    pose = np.eye(4)
    f = _frame(0, person=False, box_x=None)  # the box is gone from the room ...
    inst = mod.observe(f, pose)
    rgb_map, depth_map, gt_map = render_toy(W, H, person=False, box_x=0.9, box_z=3.0)  # ... the map still has it
    rec = mod.check_and_update(f, inst, pose, depth_map, rgb_map)
    assert rec is not None and rec.rendered_positives == 1 and rec.fixed
    assert not inst.dynamic.any()  # the wall it stood before is not a mover
    # the box, when seen again (e.g. in a keyframe), is now classified dynamic
    fb = _frame(2, person=False, box_x=0.9, box_z=3.0)
    inst_b = mod.observe(fb, pose)
    assert inst_b.dynamic[_instance_of(inst_b, fb.gt == 2) - 1]


class _ClassSegmenter:
    """A segmenter with COCO-like class names that labels the toy person 'person', the box 'box'."""

    names = {0: "person", 1: "box", 2: "chair"}

    def __init__(self, inner):
        self.inner = inner

    def segment(self, rgb, depth=None):
        from dynslam_cli.motion.types import Segmentation

        gt = self.gt
        ids = np.zeros(gt.shape, np.int32)
        ids[gt == 1], ids[gt == 2] = 1, 2
        return Segmentation(ids, np.array([0, 1], np.int64), np.ones(2, np.float32))


def test_module_prior_classes_or_rule_and_errors():
    from dynslam_cli.motion.module import prior_class_ids

    seg = _ClassSegmenter(None)
    assert prior_class_ids(seg, []).tolist() == []
    assert prior_class_ids(seg, ["person", "chair"]).tolist() == [0, 2]
    with pytest.raises(DynslamError, match="no class dog"):
        prior_class_ids(seg, ["dog"])
    with pytest.raises(DynslamError, match="needs a segmenter with class names.*GeometricSegmenter"):
        _module(prior_classes=["person"])  # the weightless segmenter has no classes
    mod = _module()
    mod.segmenter = seg
    f0 = _frame(0)
    seg.gt = f0.gt
    inst = mod.observe(f0, np.eye(4))
    assert inst.dynamic.tolist() == [False, False] and inst.prior_probs is None  # g starts static
    mod.prior_class_ids = prior_class_ids(seg, ["person"])
    inst = mod.observe(f0, np.eye(4))
    assert inst.dynamic.tolist() == [True, False] and inst.prior_probs.tolist() == [1.0, 0.0]
    assert inst.static_mask[f0.gt == 1].sum() == 0 and inst.static_mask[f0.gt == 2].all()
    kept = mod.keyframe_instances(inst)  # keyframes keep the class prior through re-classification
    assert mod.dynamic_ids(*kept).tolist() == [1]
    # after the check the class prior still holds (the OR rule), whatever g learned
    mod.check_and_update(f0, inst, np.eye(4), f0.depth, None)
    assert inst.dynamic[0]


def test_module_prior_or_rule_and_state_dict_round_trip(tmp_path):
    from dynslam_cli.motion.classifier import MotionClassifier, save_prior

    f0 = _frame(0)
    probe = _module()
    inst = probe.observe(f0, np.eye(4))
    pid = _instance_of(inst, f0.gt == 1)
    prior = MotionClassifier(probe.encoder.dim, 16, lr=0.05, seed=0)
    labels = np.zeros(inst.count, np.float32)
    labels[pid - 1] = 1
    prior.fit_steps(inst.embeddings, labels, max_steps=300)
    path = save_prior(tmp_path / "prior.pt", prior, "color-hist", {})

    mod = _module(prior=str(path), centre_feature=True)
    inst = mod.observe(f0, np.eye(4))
    assert inst.dynamic[pid - 1] and inst.prior_probs[pid - 1] > 0.5  # prior says person → dynamic
    assert inst.embeddings.shape[1] == mod.encoder.dim and mod.in_dim == mod.encoder.dim + 3
    kept = mod.keyframe_instances(inst)
    assert mod.dynamic_ids(*kept).tolist() == [pid]
    rec = mod.check_and_update(f0, inst, np.eye(4), render_toy(W, H, person=False)[1], None)
    assert rec is not None  # the online g learns the person too
    state = mod.state_dict()
    torch.save(state, tmp_path / "ck.pt")
    mod2 = _module(prior=str(path), centre_feature=True)
    mod2.load_state_dict(torch.load(tmp_path / "ck.pt", weights_only=True))
    f1 = _frame(1, person_x=0.1)
    a, b = mod.observe(f1, np.eye(4)), mod2.observe(f1, np.eye(4))
    assert np.allclose(a.probs, b.probs) and np.array_equal(a.dynamic, b.dynamic)
    assert mod2.dynamic_ids(*kept).tolist() == mod.dynamic_ids(*kept).tolist()
    assert len(mod2.replay) == len(mod.replay) and mod2.updates == mod.updates
    with pytest.raises(DynslamError, match="saved with encoder"):
        _module().load_state_dict(state)


def test_module_with_effnet_encoder(tmp_path, monkeypatch):
    monkeypatch.setenv("DYNSLAM_CACHE", str(tmp_path / "cache"))
    mod = _module("effnet-lite0")
    f0 = _frame(0)
    inst = mod.observe(f0, np.eye(4))
    assert inst.embeddings.shape == (inst.count, 1280)
    rec = mod.check_and_update(f0, inst, np.eye(4), render_toy(W, H, person=False)[1], None)
    assert rec is not None and inst.dynamic[_instance_of(inst, f0.gt == 1) - 1]
    f1 = _frame(1, person_x=0.2)
    inst1 = mod.observe(f1, np.eye(4))
    assert inst1.dynamic[_instance_of(inst1, f1.gt == 1) - 1]
    assert (tmp_path / "cache" / "effnet-lite0-160-v1.onnx").is_file()  # motion.encoder_input_size 0: 160


def test_module_learns_what_the_backend_saw_move():
    # the map agrees with the frame (the person was mapped where it stands: nothing 0.3 m off), but
    # the backend's keypoints on it stopped reprojecting: the vote labels it moving, g learns it
    mod = _module()
    pose = np.eye(4)
    f0 = _frame(0, person_x=-0.3)
    inst = mod.observe(f0, pose)
    pid = _instance_of(inst, f0.gt == 1)
    assert mod.check_and_update(f0, inst, pose, f0.depth, None) is None  # consistent: nothing to learn
    vote = np.zeros(inst.count, bool)
    vote[pid - 1] = True
    rec = mod.check_and_update(f0, inst, pose, f0.depth, None, None, None, vote)
    assert rec is not None and rec.labels[rec.contradicted[0]] == 1 and mod.updates == 1
    assert inst.dynamic[pid - 1] and inst.dynamic.sum() == 1
    # stayed put overrides it (an object set down at its new place is static there)
    rec = mod.check_and_update(f0, inst, pose, f0.depth, None, None, vote, vote)
    assert rec is not None and not any(rec.labels)


def _instance_centres_numpy(depth, ids, k, intr, pose_c2w, step=2):
    """The numpy expression the kernel replaced (the reference it must match bit for bit)."""
    fx, fy, cx, cy = intr
    d, im = depth[::step, ::step], ids[::step, ::step]
    vs, us = np.mgrid[0:depth.shape[0]:step, 0:depth.shape[1]:step]
    m = (d > 0) & (im > 0) & np.isfinite(d)
    z = d[m].astype(np.float64)
    pts = np.stack([(us[m] - cx) / fx * z, (vs[m] - cy) / fy * z, z], 1)
    lab = im[m] - 1
    cnt = np.bincount(lab, minlength=k)[:k].astype(np.float64)
    c = np.stack([np.bincount(lab, pts[:, j], minlength=k)[:k] for j in range(3)], 1) if k else np.zeros((0, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        c = c / cnt[:, None]
    T = np.asarray(pose_c2w, np.float64)
    return (c @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def test_instance_centres_match_the_numpy_expression_bit_for_bit():
    from dynslam_cli.motion._instance_kernels import instance_sums
    from dynslam_cli.motion.module import instance_centres

    rng = np.random.default_rng(0)
    pose = np.eye(4)
    pose[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    pose[:3, 3] = [0.3, -1.2, 2.0]
    intr = (525.0, 523.5, 319.5, 239.5)
    for t in range(12):
        h, w = rng.integers(5, 60, 2)
        depth = rng.uniform(0.2, 6.0, (h, w)).astype(np.float32 if t % 2 else np.float64)
        depth[rng.random((h, w)) < 0.2] = 0.0
        depth[rng.random((h, w)) < 0.05] = np.nan
        depth[rng.random((h, w)) < 0.05] = np.inf
        ids = rng.integers(-1, 8, (h, w)).astype(np.int32 if t % 3 else np.int64)
        for k in (0, 3, 7, 9):  # ids above k are not counted; instance 8 of 9 may have no pixel (NaN)
            for step in (1, 2):
                got = instance_centres(depth, ids, k, intr, pose, step)
                want = _instance_centres_numpy(depth, ids, k, intr, pose, step)
                assert got.shape == (k, 3) and got.dtype == np.float32
                np.testing.assert_array_equal(got, want)
        # and the kernel's float64 sums themselves, before the cast to float32 hides their last bits
        sums, cnt = instance_sums(depth, ids, 7, *intr, 2)
        d, im = depth[::2, ::2], ids[::2, ::2]
        vs, us = np.mgrid[0:h:2, 0:w:2]
        m = (d > 0) & (im > 0) & (im <= 7) & np.isfinite(d)
        z = d[m].astype(np.float64)
        lab = im[m] - 1
        np.testing.assert_array_equal(cnt, np.bincount(lab, minlength=7).astype(np.float64))
        for j, col in enumerate(((us[m] - intr[2]) / intr[0] * z, (vs[m] - intr[3]) / intr[1] * z, z)):
            np.testing.assert_array_equal(sums[:, j], np.bincount(lab, col, minlength=7))


class TestPerceive:
    """perceive(): what the frame's pixels alone decide; observe(seen=...) classifies it as observe() would."""

    def test_observe_from_perception_equals_observe(self):
        f = _frame(0, person_x=-0.3)
        mod = _module()
        seen = mod.perceive(f)
        assert seen.frame_index == 0 and seen.seg.count == seen.embeddings.shape[0] >= 3
        assert set(seen.timings) == {"segment", "encode"}
        a = mod.observe(f, np.eye(4), seen)
        b = mod.observe(f, np.eye(4))
        assert np.array_equal(a.ids, b.ids) and np.array_equal(a.embeddings, b.embeddings)
        assert np.array_equal(a.static_mask, b.static_mask) and np.array_equal(a.probs, b.probs)
        assert a.timings["segment"] == seen.timings["segment"] and "classify" in a.timings

    def test_perception_does_not_depend_on_the_classifier(self):
        f = _frame(0, person_x=-0.3)
        mod = _module()
        before = mod.perceive(f)
        inst = mod.observe(f, np.eye(4), before)
        room_depth = render_toy(W, H, person=False)[1]
        assert mod.check_and_update(f, inst, np.eye(4), room_depth[::2, ::2], None) is not None  # g learnt
        after = mod.perceive(f)
        assert np.array_equal(before.seg.ids, after.seg.ids)
        assert np.array_equal(before.embeddings, after.embeddings)
        assert mod.observe(f, np.eye(4), after).dynamic.sum() == 1  # the classifier, not the perception, changed


def test_static_mask_dilates_the_ids_not_the_extent():
    mod = _module(mask_dilation=4 / W)  # 4 px
    ids = np.zeros((H, W), np.int32)
    ids[10:20, 10:20] = 1  # the dynamic instance's own pixels
    ids[30:40, 30:40] = 2  # a static one
    extent = ids.copy()
    extent[10:20, 20:26] = 1  # its outline band, taken from where something new stands
    dyn = np.array([True, False])
    plain = mod._static_mask(ids, dyn)
    assert not plain[6:24, 6:24].any() and plain[12, 25] and plain[35, 35]  # 4 px around the ids only
    with_ext = mod._static_mask(ids, dyn, extent)
    assert not with_ext[10:20, 20:26].any()  # the band is masked ...
    assert with_ext[12, 27] and with_ext[12, 29]  # ... but not dilated: the pixels beside it stay usable
    np.testing.assert_array_equal(with_ext | (extent == 1), plain | (extent == 1))
    assert mod._static_mask(ids, np.array([False, False]), extent).all()
