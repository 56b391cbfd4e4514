"""The motion module the SLAM loop calls: segment + encode + classify each frame, check it against
the map after tracking, update the classifier on contradiction (with replay), and re-classify the
stored instances of the keyframes so the map forgets what moved."""

from __future__ import annotations

import time
from types import SimpleNamespace
from typing import Optional

import numpy as np
import torch

from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.check import check_size, inconsistency_check
from dynslam_cli.motion.checkable import bounded_extent
from dynslam_cli.motion.classifier import MotionClassifier, ReplayBuffer, load_prior, update_with_replay
from dynslam_cli.motion.encoders import make_encoder
from dynslam_cli.motion.segment_geometric import GeometricSegmenter
from dynslam_cli.motion.segmenters import make_segmenter
from dynslam_cli.motion.types import FrameInstances, Perception, UpdateRecord, intrinsics_tuple

# The classifier g: a 2-layer MLP of this many hidden units, Adam at this learning rate, at most UPDATE_STEPS and at
# least MIN_UPDATE_STEPS steps per update (then it stops once the contradictions are fixed); a reservoir replay
# buffer of REPLAY_CAPACITY instances seen dynamic.
HIDDEN = 128
LR = 0.005
UPDATE_STEPS = 50
MIN_UPDATE_STEPS = 5
REPLAY_CAPACITY = 1000
# Instances with fewer valid pixels at check resolution are not judged.
MIN_CHECK_PIXELS = 12
# Backward check: current instances are not labelled moving where they show what a departed object uncovered (that
# is the static background; the departed object's rendered segment is labelled dynamic either way).
BACKWARD_CURRENT = False




def dilation_radius(fraction: float, width: int) -> int:
    """Mask dilation in pixels for an image ``width`` pixels wide."""
    return max(0, int(round(float(fraction) * int(width))))


def prior_class_ids(segmenter, names) -> np.ndarray:
    """Class ids of ``names`` in the segmenter's class list (``motion.prior_classes``)."""
    names = [str(n) for n in (names or [])]
    if not names:
        return np.zeros(0, np.int64)
    table = getattr(segmenter, "names", None) or {}
    if not table:
        raise DynslamError(f"motion.prior_classes={names} needs a segmenter with class names (yolo-seg with a "
                           f"YOLOv8-seg model); {type(segmenter).__name__} has none")
    missing = [n for n in names if n not in table.values()]
    if missing:
        raise DynslamError(f"motion.prior_classes: no class {', '.join(missing)} in the segmenter model "
                           f"(it has e.g. {', '.join(list(table.values())[:5])})")
    return np.array(sorted(k for k, v in table.items() if v in names), np.int64)


def instance_centres(depth: np.ndarray, ids: np.ndarray, k: int, intr: tuple, pose_c2w: np.ndarray,
                     step: int = 2) -> np.ndarray:
    """(k, 3) world-frame mean of the back-projected valid pixels of each instance (NaN if none)."""
    from dynslam_cli.motion._instance_kernels import instance_sums

    fx, fy, cx, cy = (float(v) for v in intr)
    c, cnt = instance_sums(np.asarray(depth), np.asarray(ids), int(k), fx, fy, cx, cy, int(step))
    with np.errstate(invalid="ignore", divide="ignore"):
        c = c / cnt[:, None]
    T = np.asarray(pose_c2w, np.float64)
    return (c @ T[:3, :3].T + T[:3, 3]).astype(np.float32)


def _usable(dynamic: np.ndarray) -> np.ndarray:
    """(K + 1,) bool by instance id (0 = background): True where the instance is not ``dynamic``."""
    lut = np.ones(len(dynamic) + 1, bool)
    lut[1:] = ~dynamic
    return lut


def _outside_extent(static: np.ndarray, dynamic: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """``static`` less the ``extent`` (H×W int32 instance map) of the instances ``dynamic``, not dilated."""
    return static & _usable(dynamic)[extent]


class MotionModule:
    def __init__(self, cfg, intrinsics, device: torch.device):
        self.cfg = cfg
        self.m = cfg.motion if hasattr(cfg, "motion") else cfg
        self.intr = intrinsics_tuple(intrinsics)
        fx, fy, cx, cy = self.intr
        self._pinhole = SimpleNamespace(fx=fx, fy=fy, cx=cx, cy=cy)  # for checkable.bounded_extent
        self.device = torch.device(device) if not isinstance(device, torch.device) else device
        m = self.m
        run = getattr(cfg, "run", None)  # run.seed / run.threads (a bare MotionConfig: 0 / onnxruntime's default)
        seed, threads = (int(run.seed), int(run.threads)) if run is not None else (0, 0)
        self.segmenter = make_segmenter(m, intrinsics, threads, self.device.type)
        self.rendered_segmenter = GeometricSegmenter.from_config(m, intrinsics)
        self.rendered_segmenter.min_instance_area = 4
        self.encoder = make_encoder(m, threads, self.device.type)
        self.in_dim = int(self.encoder.dim) + (3 if m.centre_feature else 0)
        # the classifier and the prior stay on the CPU on any run: a few small matrices per step, where a GPU
        # only adds a wait per step (on one H200 the update took 7-14 ms a frame against 5 on the host's CPU)
        self.classifier = MotionClassifier(self.in_dim, HIDDEN, LR, UPDATE_STEPS, MIN_UPDATE_STEPS, seed, "cpu")
        self.replay = ReplayBuffer(self.in_dim, REPLAY_CAPACITY, seed)
        self.prior: Optional[MotionClassifier] = None
        if m.prior:
            self.prior = load_prior(m.prior, self.encoder.name, int(self.encoder.dim), "cpu")
        self.prior_class_ids = prior_class_ids(self.segmenter, m.prior_classes)
        self.updates = 0

    # --- features
    def _features(self, emb: np.ndarray, centres: np.ndarray) -> np.ndarray:
        if not self.m.centre_feature:
            return emb.astype(np.float32)
        c = np.nan_to_num(centres.astype(np.float32))  # metres, unscaled
        return np.concatenate([emb.astype(np.float32), c], 1)

    def _classify(self, feats: np.ndarray, emb: np.ndarray,
                  class_ids: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
        p = self.classifier.probs(feats)
        pp = self.prior.probs(emb) if self.prior is not None and len(emb) else None
        if len(self.prior_class_ids) and class_ids is not None and len(class_ids) == len(p):
            pc = np.isin(class_ids, self.prior_class_ids).astype(np.float32)
            pp = pc if pp is None else np.maximum(pp, pc)
        dyn = p > 0.5
        final = p
        if pp is not None:
            dyn = dyn | (pp > 0.5)
            final = np.maximum(p, pp)
        return dyn, final.astype(np.float32), pp

    def _static_mask(self, ids: np.ndarray, dynamic: np.ndarray, extent=None) -> np.ndarray:
        """Pixels usable for tracking and mapping: outside every dynamic instance dilated by
        ``motion.mask_dilation`` (of the image width), and outside its extent (not dilated)."""
        static = _usable(dynamic)[ids]
        r = dilation_radius(self.m.mask_dilation, ids.shape[1])
        if r > 0 and not static.all():
            import cv2

            k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
            static = cv2.dilate((~static).astype(np.uint8), k) == 0
        return static if extent is None else _outside_extent(static, dynamic, extent)

    # --- per frame
    def perceive(self, frame) -> Perception:
        """Segment the frame and encode its instances: what depends on its pixels alone (thread-safe
        beside the rest of a run: no torch parameters, no numba thread pool, no shared state)."""
        t0 = time.perf_counter()
        rgb, depth = frame.rgb, frame.depth
        seg = self.segmenter.segment(rgb, depth)
        t1 = time.perf_counter()
        emb = self.encoder.encode(rgb, seg.ids) if seg.count else np.zeros((0, self.encoder.dim), np.float32)
        t2 = time.perf_counter()
        return Perception(int(getattr(frame, "index", -1)), seg, emb,
                          {"segment": (t1 - t0) * 1e3, "encode": (t2 - t1) * 1e3})

    def observe(self, frame, pose_c2w_guess: np.ndarray, seen: Optional[Perception] = None) -> FrameInstances:
        """The frame's instances classified (``seen``: its :meth:`perceive`, computed now when None).  The
        segmentation's extent, where it has one, waits in ``FrameInstances.grown`` for :meth:`bound_outline`."""
        p = self.perceive(frame) if seen is None else seen
        t2 = time.perf_counter()
        seg, emb = p.seg, p.embeddings
        centres = instance_centres(frame.depth, seg.ids, seg.count, self.intr, pose_c2w_guess)
        feats = self._features(emb, centres)
        dyn, probs, pp = self._classify(feats, emb, seg.class_ids)
        t3 = time.perf_counter()
        return FrameInstances(
            frame_index=int(getattr(frame, "index", -1)), ids=seg.ids, embeddings=emb, centres=centres,
            dynamic=dyn, probs=probs, static_mask=self._static_mask(seg.ids, dyn),
            class_ids=seg.class_ids, prior_probs=pp, grown=seg.extent,
            timings={**p.timings, "classify": (t3 - t2) * 1e3}, features=feats,
        )

    def bound_outline(self, inst: FrameInstances, depth: np.ndarray, pose_c2w: np.ndarray, keyframes,
                      static: np.ndarray, dynamic: np.ndarray) -> np.ndarray:
        """Once the frame is tracked (``pose_c2w``): ``inst.extent`` set to the part of the segmentation's extent that
        stands where the last ``keyframes`` saw empty space (:func:`~dynslam_cli.motion.checkable.bounded_extent`),
        and the pixels the map may learn from: ``static`` (:meth:`_static_mask` of the instances ``dynamic``, the ids
        dilated) less the extent of those instances (not dilated)."""
        t0 = time.perf_counter()
        if inst.grown is not None and len(keyframes):
            extent = bounded_extent(inst.ids, inst.grown, depth, pose_c2w, self._pinhole, keyframes,
                                    self.m.depth_threshold)
            inst.extent = None if extent is inst.ids else extent
        out = static if inst.extent is None else _outside_extent(static, dynamic, inst.extent)
        inst.timings["classify"] = inst.timings.get("classify", 0.0) + (time.perf_counter() - t0) * 1e3
        return out

    def _feats_of(self, inst: FrameInstances) -> np.ndarray:
        f = inst.features
        return f if f is not None else self._features(inst.embeddings, inst.centres)

    def check_and_update(self, frame, inst: FrameInstances, pose_c2w: np.ndarray, rendered_depth: np.ndarray,
                         rendered_rgb: Optional[np.ndarray],
                         forward_valid: Optional[np.ndarray] = None,
                         stationary: Optional[np.ndarray] = None,
                         reprojection_moving: Optional[np.ndarray] = None) -> Optional[UpdateRecord]:
        m = self.m
        t0 = time.perf_counter()
        H, W = frame.depth.shape[:2]
        cw, ch = check_size(H, W, m.check_width)
        fx, fy, cx, cy = self.intr  # the rendered view is segmented at check resolution
        sx, sy = cw / W, ch / H
        self.rendered_segmenter.intrinsics = (fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5)
        res = inconsistency_check(frame.depth, rendered_depth, inst.ids, m.depth_threshold, m.pixel_fraction,
                                  rendered_rgb, self.rendered_segmenter if m.bidirectional else None,
                                  m.check_width, MIN_CHECK_PIXELS, forward_valid, BACKWARD_CURRENT)
        # centres at the tracked pose
        inst.centres = instance_centres(frame.depth, inst.ids, inst.count, self.intr, pose_c2w)
        feats = self._features(inst.embeddings, inst.centres)
        inst.features = feats
        judged = res.judged if res.judged is not None else np.ones(inst.count, bool)
        labels = res.observed_moving
        if reprojection_moving is not None and len(reprojection_moving) == inst.count:  # the backend saw it move
            judged = judged | reprojection_moving
            labels = labels | reprojection_moving
        if stationary is not None and len(stationary) == inst.count:  # stayed put: static at its place
            judged = judged | stationary
            labels = labels & ~stationary
        pred = self.classifier.predict(feats)
        # things that left: encode flagged segments of the rendered view (label dynamic)
        extra = np.zeros((0, self.in_dim), np.float32)
        if rendered_rgb is not None and res.rendered_ids is not None and len(res.rendered_flagged):
            extra = self._rendered_features(res, rendered_rgb, rendered_depth, pose_c2w, frame.depth.shape)
        t1 = time.perf_counter()
        cur = np.nonzero(judged)[0]
        contradicted = cur[labels[cur] != pred[cur]]
        extra_contra = ~self.classifier.predict(extra) if len(extra) else np.zeros(0, bool)
        movers = feats[cur[labels[cur]]]
        record = None
        if len(contradicted) or extra_contra.any():
            x = np.concatenate([feats[cur], extra])
            y = np.concatenate([labels[cur].astype(np.float32), np.ones(len(extra), np.float32)])
            before, after, steps, n_rep = update_with_replay(self.classifier, self.replay if m.replay else None,
                                                             x, y, m.replay_samples)
            self.updates += 1
            new_pred = self.classifier.predict(feats)
            fixed = bool(np.all(new_pred[cur] == labels[cur])) and bool(np.all(self.classifier.predict(extra))) \
                if len(extra) else bool(np.all(new_pred[cur] == labels[cur]))
            record = UpdateRecord(
                frame=inst.frame_index, instances=int(len(cur)), labels=[int(v) for v in labels[cur]],
                predicted_before=[int(v) for v in pred[cur]],
                contradicted=[int(i) for i in np.searchsorted(cur, contradicted)],
                loss_before=before, loss_after=after, steps=int(steps), replay_used=int(n_rep),
                replay_size=0, fixed=fixed, rendered_positives=int(len(extra)),
            )
        if m.replay:
            self.replay.add(np.concatenate([movers, extra]))
        if record is not None:
            record.replay_size = len(self.replay)
        dyn, probs, pp = self._classify(feats, inst.embeddings, inst.class_ids)
        inst.dynamic, inst.probs, inst.prior_probs = dyn, probs, pp
        inst.static_mask = self._static_mask(inst.ids, dyn)
        inst.timings["check"] = (t1 - t0) * 1e3
        inst.timings["update"] = (time.perf_counter() - t1) * 1e3
        inst.check = res  # type: ignore[attr-defined]
        return record

    def _rendered_features(self, res, rendered_rgb, rendered_depth, pose_c2w, frame_hw) -> np.ndarray:
        import cv2

        rids = res.rendered_ids
        h, w = rids.shape
        lut = np.zeros(int(rids.max()) + 1, np.int32)
        lut[res.rendered_flagged] = np.arange(1, len(res.rendered_flagged) + 1)
        sub = lut[rids]
        rgb = rendered_rgb
        if rgb.dtype != np.uint8:
            rgb = np.clip(rgb * (255.0 if rgb.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA) if rgb.shape[:2] != (h, w) else rgb
        emb = self.encoder.encode(rgb, sub)
        ren = cv2.resize(rendered_depth.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
        fx, fy, cx, cy = self.intr
        H, W = frame_hw
        sx, sy = w / W, h / H
        intr = (fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5)
        centres = instance_centres(ren, sub, len(emb), intr, pose_c2w, step=1)
        return self._features(emb, centres)

    # --- keyframes (kept in the keyframe store, slam/keyframes.KeyframeStore)
    def keyframe_instances(self, inst: FrameInstances) -> tuple[np.ndarray, np.ndarray]:
        """What a keyframe keeps of the frame's instances to re-classify them later: the
        classifier's features and the class prior (bool), one row per instance."""
        pp = inst.prior_probs if inst.prior_probs is not None else np.zeros(inst.count, np.float32)
        return self._feats_of(inst).astype(np.float32), pp > 0.5

    def dynamic_ids(self, feats: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """The instance ids (row + 1) the current classifier (or the class prior) calls dynamic."""
        dyn = self.classifier.predict(feats) | prior if len(feats) else np.zeros(0, bool)
        return (np.nonzero(dyn)[0] + 1).astype(np.int32)

    # --- checkpoint
    def state_dict(self) -> dict:
        """Tensors and plain Python values only (loads with ``torch.load(..., weights_only=True)``)."""
        return {"classifier": self.classifier.state_dict(), "replay": self.replay.state_dict(),
                "updates": self.updates, "encoder": self.encoder.name, "in_dim": self.in_dim}

    def load_state_dict(self, d: dict) -> None:
        if d.get("encoder") != self.encoder.name or int(d.get("in_dim", -1)) != self.in_dim:
            raise DynslamError(f"motion state was saved with encoder {d.get('encoder')} ({d.get('in_dim')}-d), "
                               f"this run uses {self.encoder.name} ({self.in_dim}-d)")
        self.classifier.load_state_dict(d["classifier"])
        self.replay.load_state_dict(d["replay"])
        self.updates = int(d["updates"])
