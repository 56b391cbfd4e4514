"""One frame of dynamic mode: the paper's 'learn to memorize and to forget' loop.

Per frame: segment, encode and classify the instances (motion module) → track on the static
pixels → render the map at the tracked pose and run the bidirectional inconsistency check → on a
contradiction update the classifier (with replay) and refresh every keyframe's usable rays (the
map forgets what moved) → map / bundle-adjust with the static mask, storing the instance ids of
the keyframe's rays.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.utils.io import atomic_path, write_text_atomic

# A pixel is inconsistent only when no rendered depth within this many pixels (at check resolution) agrees with the
# observation.
CHECK_RADIUS = 1
# No inconsistency check before this frame: the map needs a keyframe and a bundle adjustment beyond frame 0 to judge
# anything.
CHECK_WARMUP = 5
# When a classifier update newly marks more than this fraction of the frame's valid pixels dynamic, the frame is
# tracked again without them (the paper tracks once).
RETRACK_FRACTION = 0.02


class DynamicLoop:
    """Drives a :class:`~dynslam_cli.slam.system.SLAM` with a
    :class:`~dynslam_cli.motion.module.MotionModule` frame by frame."""

    def __init__(self, cfg, intrinsics, slam, device, mask_dir: Optional[Path] = None):
        from dynslam_cli.motion.module import MotionModule

        self.cfg = cfg
        self.slam = slam
        self.mm = MotionModule(cfg, intrinsics, device)
        self.mask_dir = mask_dir
        self.records: list[dict] = []
        self.width = int(intrinsics.width)
        self.check_radius = CHECK_RADIUS
        self.warmup = CHECK_WARMUP
        self.retrack_fraction = RETRACK_FRACTION
        self.still_frames = int(cfg.run.still_frames)
        self.still_tolerance = float(cfg.run.still_tolerance)
        self.forget_radius = float(cfg.run.forget_radius)
        self.carve_margin = float(cfg.run.carve_margin)
        self.last_masks: Optional[np.ndarray] = None  # the last frame's dynamic mask (for callers)

    # ------------------------------------------------------------------ per frame
    def _guess(self, frame) -> np.ndarray:
        if self.slam.n_frames == 0:
            gt = getattr(frame, "pose_c2w", None)
            return np.array(gt, np.float64) if gt is not None else np.eye(4)
        return self.slam.predict_pose()

    def _refresh_keyframes(self) -> int:
        """Recompute every keyframe's usable rays from the current classifier, and drop the backend
        landmarks made on instances now called dynamic; returns rays masked."""
        masked = 0
        for fid in self.mm.keyframes:
            self.slam.forget_landmarks(fid, self.mm.keyframe_dynamic_ids(fid))
        for kf in self.slam.keyframes:
            if kf.frame_id not in self.mm.keyframes:
                continue
            dyn_ids = self.mm.keyframe_dynamic_ids(kf.frame_id)
            kf.usable = ~np.isin(kf.instance_ids, dyn_ids)
            if kf.near_ids is not None:  # rays within the mask dilation of a dynamic instance
                kf.usable &= ~np.isin(kf.near_ids, dyn_ids).any(axis=1)
            gone = getattr(kf, "gone", None)
            if gone is not None:  # surfaces seen gone stay forgotten
                kf.usable &= ~gone
            masked += int((~kf.usable).sum())
        return masked

    def checkable_depth(self, depth: np.ndarray, pose_c2w: np.ndarray, step: int = 4):
        """What of the observed depth the map can judge: returns ``(depth, forward_ok)``.

        ``depth`` is the observation with these pixels set to 0 (invalid):

        - pixels within 2 px of a depth discontinuity (relative jump > 5 %), where a one-pixel
          misalignment between the reduced-resolution render and the observation reads as metres;
        - pixels whose 3-D point lies outside the view frustum of every recent keyframe: newly
          revealed space the map never observed, whose rendered depth means nothing.

        ``forward_ok`` (bool) marks the pixels where "observed in front of the map" is evidence of
        motion: some keyframe saw the point or the free space where it now is, not an occluder in
        front of it (space hidden behind an occluder is unknown to the map too).  "Observed behind
        the map" (a mapped thing left) is judged on every valid pixel.
        """
        from dynslam_cli.slam.keyframes import depth_edges, keyframe_visibility

        d = depth.astype(np.float32)
        out = np.where((d > 0) & ~depth_edges(d, 0.05, 2), d, 0.0).astype(np.float32)
        kfs = self.slam.keyframes
        if not kfs:
            return out, out > 0
        frustum, observed = keyframe_visibility(d, pose_c2w, self.slam.intr, kfs[-self.frustum_keyframes:], step,
                                                self.mm.m.depth_threshold)
        out[~frustum] = 0.0
        return out, observed

    def stationary(self, depth: np.ndarray, ids: np.ndarray, pose_c2w: np.ndarray) -> Optional[np.ndarray]:
        """Instances whose points stayed within ``run.still_tolerance`` (0 = motion.depth_threshold)
        of the depth every keyframe of the last ``run.still_frames`` frames saw there (see
        :func:`~dynslam_cli.slam.keyframes.stationary_instances`); None when ``run.still_frames``
        is 0.  It breaks the loop where a static surface once labelled dynamic is never mapped and
        so always looks 'in front of the map'.  With ``motion.centre_feature``, where 'static' is
        learnt at the place only, the window is half as long."""
        centre = bool(self.mm.m.centre_feature)
        frames = self.still_frames // 2 if centre else self.still_frames
        if frames < 2:
            return None
        from dynslam_cli.slam.keyframes import stationary_instances

        now = self.slam.n_frames - 1
        window = [kf for kf in self.slam.keyframes if now - frames <= kf.frame_id < now]
        tol = self.still_tolerance if self.still_tolerance > 0 else self.mm.m.depth_threshold
        return stationary_instances(depth, ids, pose_c2w, self.slam.intr, window, tol)

    def forget_departed(self, res, observed: np.ndarray, rendered: np.ndarray, pose_c2w: np.ndarray) -> int:
        """With ``run.forget_radius`` > 0: the keyframe rays on the surface of what the backward
        check saw leave (flagged rendered segments, where the observation lies more than t_d
        behind the map) are marked gone, so the map stops replaying a departed object even when
        the classifier does not recognise its keyframe crops.  Returns the rays newly marked."""
        if self.forget_radius <= 0 or res is None or res.rendered_ids is None or not len(res.rendered_flagged):
            return 0
        import cv2

        from dynslam_cli.geometry.camera import pixel_dirs, transform
        from dynslam_cli.slam.keyframes import forget_near

        rids = res.rendered_ids
        h, w = rids.shape
        ren = cv2.resize(rendered.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
        obs = cv2.resize(observed.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
        left = np.isin(rids, res.rendered_flagged) & (ren > 0) & (obs > 0) & (obs - ren > self.mm.m.depth_threshold)
        if not left.any():
            return 0
        intr = self.slam.intr
        sx, sy = w / observed.shape[1], h / observed.shape[0]
        fx, fy, cx, cy = intr.fx * sx, intr.fy * sy, (intr.cx + 0.5) * sx - 0.5, (intr.cy + 0.5) * sy - 0.5
        vs, us = np.nonzero(left)
        pw = transform(pose_c2w, pixel_dirs(us, vs, fx, fy, cx, cy) * ren[vs, us][:, None])
        return forget_near(self.slam.keyframes, pw, intr, self.forget_radius)

    def carve(self, depth: np.ndarray, static_mask: np.ndarray) -> int:
        """With ``run.carve_margin`` > 0, judged on the newest keyframe's static pixels, the earlier
        keyframes' rays are marked gone where the scene changed along them: the newest keyframe
        sees through their surface point (it has left: a picked-up box, a person who walked on),
        or sees a surface in the free space they crossed (something arrived: the box set down
        elsewhere). Returns the rays newly marked."""
        kfs = self.slam.keyframes
        if self.carve_margin <= 0 or len(kfs) < 2:
            return 0
        from dynslam_cli.slam.keyframes import forget_overtaken, forget_seen_through

        d = np.where(static_mask, np.asarray(depth, np.float32), 0).astype(np.float32)
        window = max(1, int(round(3 * self.width / 640)))
        pose, intr = kfs[-1].pose_c2w, self.slam.intr
        n = forget_seen_through(kfs[:-1], d, pose, intr, self.carve_margin, window)
        return n + forget_overtaken(kfs[:-1], d, pose, intr, self.carve_margin, max(1, int(round(2 * self.width / 320))))

    def near_ids(self, ids: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """(M, 2) int32: the largest and smallest instance id within the mask dilation radius of
        each keyframe ray ``pixels`` (u, v), so that re-masking a keyframe after a classifier
        update dilates dynamic instances as the live mask does."""
        import cv2

        from dynslam_cli.motion.module import dilation_radius

        r = dilation_radius(self.mm.m.mask_dilation, ids.shape[1])
        u, v = pixels[:, 0].astype(np.int64), pixels[:, 1].astype(np.int64)
        own = ids[v, u].astype(np.int32)
        if r <= 0:
            return np.stack([own, own], 1)
        k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        f = ids.astype(np.float32)  # exact for ids < 2^24
        hi = cv2.dilate(f, k)[v, u].astype(np.int32)
        lo = cv2.erode(f, k)[v, u].astype(np.int32)
        return np.stack([hi, lo], 1)

    @staticmethod
    def closest_rendered(rendered: np.ndarray, observed: np.ndarray, radius: int = 1) -> np.ndarray:
        """Per pixel, the rendered depth within ``radius`` pixels that is closest to the observed one.

        The map is smoother than the sensor (object edges blur into the background at reduced
        resolution), so a pixel only counts as inconsistent when *no* nearby rendered depth agrees
        with the observation: a mover's interior still differs everywhere, a blurred edge does not.
        """
        import cv2

        h, w = rendered.shape
        obs = cv2.resize(observed.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
        pad = np.pad(rendered.astype(np.float32), radius, mode="edge")
        best = rendered.astype(np.float32).copy()
        err = np.where(best > 0, np.abs(best - obs), np.inf)
        for dy in range(2 * radius + 1):
            for dx in range(2 * radius + 1):
                cand = pad[dy:dy + h, dx:dx + w]
                e = np.where(cand > 0, np.abs(cand - obs), np.inf)
                better = e < err
                best[better] = cand[better]
                err[better] = e[better]
        return np.where(obs > 0, best, rendered).astype(np.float32)

    frustum_keyframes = 20  # keyframes whose frusta count as 'observed space' for the check

    def process(self, frame, stamp: str) -> dict:
        """Process one frame; returns the per-component timings (ms) and what happened."""
        t0 = time.perf_counter()
        inst = self.mm.observe(frame, self._guess(frame))
        tr = self.slam.track(frame, inst.static_mask)
        t_track = tr.ms
        t_render = 0.0
        record = None
        retracked = False
        if self.slam.n_frames > max(1, self.warmup):  # a map built from one frame is too immature to judge
            t1 = time.perf_counter()
            scale = min(1.0, self.mm.m.check_width / float(self.width))
            r_depth, r_rgb = self.slam.render(tr.pose_c2w, scale=scale)
            raw_depth = r_depth
            t_render = (time.perf_counter() - t1) * 1e3
            judged_depth, forward_ok = self.checkable_depth(frame.depth, tr.pose_c2w)
            judged = dataclasses.replace(frame, depth=judged_depth)
            if self.check_radius > 0:
                r_depth = self.closest_rendered(r_depth, judged.depth, self.check_radius)
            before = inst.static_mask.copy()
            record = self.mm.check_and_update(judged, inst, tr.pose_c2w, r_depth, r_rgb, forward_ok,
                                              self.stationary(frame.depth, inst.ids, tr.pose_c2w))
            self.forget_departed(getattr(inst, "check", None), judged.depth, raw_depth, tr.pose_c2w)
            if record is not None and self.retrack_fraction > 0:
                valid = np.asarray(frame.depth) > 0
                newly = int((before & ~inst.static_mask & valid).sum())
                if newly > self.retrack_fraction * max(1, int(valid.sum())):
                    tr = self.slam.retrack(frame, inst.static_mask)
                    t_track += tr.ms
                    retracked = True
            if self.mask_dir is not None:  # the rendered depth beside the masks (montage plots)
                self._write_png(self.mask_dir.parent / "renders" / f"{stamp}_depth.png",
                                np.clip(raw_depth * 5000.0, 0, 65535).astype(np.uint16))
        masked = None
        if record is not None:
            rec = record.to_json()
            rec["timestamp"] = stamp
            masked = self._refresh_keyframes()
            rec["keyframe_rays_masked"] = masked
            rec["retracked"] = retracked
            self.records.append(rec)
        n_kf = len(self.slam.keyframes)
        mr = self.slam.map(frame, inst.static_mask, inst.ids)
        if len(self.slam.keyframes) > n_kf:
            kf = self.slam.keyframes[-1]
            kf.near_ids = self.near_ids(inst.ids, kf.pixels)
            self.mm.register_keyframe(kf.frame_id, inst)
            self.carve(frame.depth, inst.static_mask)
        fid = self.slam.n_frames - 1
        if self.slam.backend_keyframe and fid not in self.mm.keyframes:  # its landmarks carry these ids
            self.mm.register_keyframe(fid, inst)
        dyn_mask = inst.dynamic_mask()
        self.last_masks = dyn_mask
        if self.mask_dir is not None:
            self._write_png(self.mask_dir / f"{stamp}.png", dyn_mask.astype(np.uint8) * 255)
        tm = inst.timings
        return {
            "segment": tm.get("segment", 0.0), "encode": tm.get("encode", 0.0),
            "classify": tm.get("classify", 0.0), "track": t_track, "render": t_render,
            "check": tm.get("check", 0.0), "update": tm.get("update", 0.0),
            "map": 0.0 if mr is None else mr.ms, "frame": (time.perf_counter() - t0) * 1e3,
            "_loss": tr.loss, "_dynamic": int(inst.dynamic.sum()), "_updated": record is not None,
            "_retracked": retracked,
        }

    # ------------------------------------------------------------------ outputs and state
    @staticmethod
    def _write_png(path: Path, image: np.ndarray) -> None:
        import cv2

        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), image):
                raise OSError(f"cannot write {path}")

    def write_updates(self, path: Path) -> Path:
        return write_text_atomic(path, "".join(json.dumps(r) + "\n" for r in self.records))

    def state_dict(self) -> dict:
        return {"motion": self.mm.state_dict(), "records": list(self.records)}

    def load_state_dict(self, d: dict) -> None:
        self.mm.load_state_dict(d["motion"])
        self.records = list(d["records"])
