"""The per-frame loop of both modes: the paper's 'learn to memorize and to forget' loop.

Per frame: segment, encode and classify the instances (motion module) → track on the static
pixels → render the map at the tracked pose and run the bidirectional inconsistency check, beside
the backend's vote on the instances whose keypoints stopped reprojecting (``reprojection``) → on a
contradiction update the classifier (with replay) and refresh every keyframe's usable rays (the
map forgets what moved) → map / bundle-adjust with the frame's static mask from before its check
(what the check found reaches the keyframe at the next update), storing the instance ids of the
keyframe's rays.  The check and what follows it run on every ``motion.check_every``-th frame
(every frame by default, as in the paper).  The pieces live in ``dynslam_cli/motion/``: ``module``
(segment, encode, classify, check and update), ``checkable`` (what the map can judge),
``reprojection`` (the backend's vote), ``stayed`` (stayed put) and ``forget`` (keyframe rays masked
or gone); this loop only drives them.  Static mode is the same loop without a motion module:
every pixel is static, nothing is checked or forgotten.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.motion.checkable import checkable_depth, closest_rendered
from dynslam_cli.map.mesh import drop_vertices
from dynslam_cli.motion.forget import (DepartedPlaces, departed_points, departed_surface, forget_near, near_ids,
                                      refresh_keyframes)
from dynslam_cli.motion.reprojection import moving_by_reprojection
from dynslam_cli.motion.stayed import stayed_put, window_frames
from dynslam_cli.slam.frontend import first_pose
from dynslam_cli.utils.io import atomic_path, write_jsonl_atomic

# A pixel is inconsistent only when no rendered depth within this many pixels (at check resolution) agrees with the
# observation.
CHECK_RADIUS = 1
# No inconsistency check before this frame: the map needs a keyframe and a bundle adjustment beyond frame 0 to judge
# anything.
CHECK_WARMUP = 5
# When a classifier update newly marks more than this fraction of the frame's valid pixels dynamic, the frame is
# tracked again without them (the paper tracks once).
RETRACK_FRACTION = 0.02


# What a run times per frame (ms); the motion module's parts are 0 in static mode.  segment and encode run one frame
# ahead, beside the frame before (run/ahead.py): "wait" is the time the loop waited for them and the frame's reading,
# "frame" the frame's wall time with that wait.  "judge": what decides beside the classifier's check (the checkable
# region, stayed put, the backend's vote, forgetting departed things); "keyframes": re-masking the stored keyframes
# after an update and tagging a new keyframe's instances.
TIMED = ("segment", "encode", "classify", "track", "render", "check", "update", "judge", "keyframes", "map", "wait",
         "frame")


def this_frames_events(events: list[dict], frame: int) -> list[str]:
    """The kinds of ``frame``'s events in ``events`` (appended in frame order: read from the end)."""
    out = []
    for e in reversed(events):
        if e["frame"] < frame:
            break
        if e["frame"] == frame:
            out.append(e["kind"])
    return out[::-1]


class FrameLoop:
    """Drives a :class:`~dynslam_cli.slam.system.SLAM` frame by frame, with a
    :class:`~dynslam_cli.motion.module.MotionModule` in dynamic mode (``run.mode``; ``mm`` is None
    in static mode)."""

    def __init__(self, cfg, intrinsics, slam, device, mask_dir: Optional[Path] = None):
        self.cfg = cfg
        self.slam = slam
        self.mm = None
        if cfg.run.mode == "dynamic":
            from dynslam_cli.motion.module import MotionModule

            self.mm = MotionModule(cfg, intrinsics, device)
        self.mask_dir = mask_dir if self.mm is not None else None
        self.records: list[dict] = []
        self.frame_rows: list[dict] = []  # one per processed frame (frames.jsonl)
        self.width = int(intrinsics.width)
        self.still_seconds = float(cfg.run.still_seconds)
        self.still_tolerance = float(cfg.run.still_tolerance)
        self.forget_radius = float(cfg.run.forget_radius)
        self.departed = DepartedPlaces()  # where the check saw something leave (the mesh's departed surfaces)
        self.last_masks: Optional[np.ndarray] = None  # the last frame's dynamic mask (for callers)

    # ------------------------------------------------------------------ per frame
    def _guess(self, frame) -> np.ndarray:
        return first_pose(frame) if self.slam.n_frames == 0 else self.slam.predict_pose()

    def perceive(self, frame):
        """What the motion module decides from the frame's pixels alone (segments, embeddings), for
        :meth:`process`'s ``seen``; None in static mode.  Safe to run in another thread while this
        loop processes the frame before."""
        return None if self.mm is None else self.mm.perceive(frame)

    def process(self, frame, stamp: str, seen=None) -> dict:
        """Process one frame (``seen``: its :meth:`perceive`, else computed here); returns the
        per-component timings (ms, :data:`TIMED`) and what happened."""
        t0 = time.perf_counter()
        inst = None if self.mm is None else self.mm.observe(frame, self._guess(frame), seen)
        static = None if inst is None else inst.static_mask
        dyn_before = None if inst is None else inst.dynamic.copy()
        tr = self.slam.track(frame, static)
        t_track = tr.ms
        row = {"frame": self.slam.n_frames - 1, "timestamp": stamp, "tracked": tr.reason, "inliers": tr.inliers}
        t_render = t_judge = t_keyframes = 0.0
        record = None
        retracked = False
        checked = (inst is not None and self.slam.n_frames > max(1, CHECK_WARMUP)  # a one-frame map judges nothing
                   and (self.slam.n_frames - 1) % self.mm.m.check_every == 0)  # on every check_every-th frame
        if checked:
            t1 = time.perf_counter()
            scale = min(1.0, self.mm.m.check_width / float(self.width))
            r_depth, r_rgb = self.slam.render(tr.pose_c2w, scale=scale)
            raw_depth = r_depth
            t_render = (time.perf_counter() - t1) * 1e3
            t1 = time.perf_counter()
            judged_depth, forward_ok = checkable_depth(frame.depth, tr.pose_c2w, self.slam.intr, self.slam.keyframes,
                                                       self.mm.m.depth_threshold,
                                                       border=self.slam.cfg.tracking.ignore_border)
            judged = dataclasses.replace(frame, depth=judged_depth)
            if CHECK_RADIUS > 0:
                r_depth = closest_rendered(r_depth, judged.depth, CHECK_RADIUS)
            still_frames = window_frames(self.still_seconds, self.slam.timestamps)
            still = stayed_put(frame.depth, inst.ids, tr.pose_c2w, self.slam.intr, self.slam.keyframes,
                               self.slam.n_frames - 1, still_frames, self.still_tolerance,
                               self.mm.m.depth_threshold, bool(self.mm.m.centre_feature))
            evidence = self.slam.reprojection_evidence()
            moved = None if evidence is None else moving_by_reprojection(inst.ids, *evidence, inst.count)
            t_judge = (time.perf_counter() - t1) * 1e3
            record = self.mm.check_and_update(judged, inst, tr.pose_c2w, r_depth, r_rgb, forward_ok, still, moved)
            t1 = time.perf_counter()
            if self.forget_radius > 0:
                left = departed_points(getattr(inst, "check", None), judged.depth, raw_depth, tr.pose_c2w,
                                       self.slam.intr, self.mm.m.depth_threshold)
                forget_near(self.slam.keyframes, left, self.slam.intr, self.forget_radius)
                self.departed.add(left)
            t_judge += (time.perf_counter() - t1) * 1e3
            if record is not None and RETRACK_FRACTION > 0:
                valid = np.asarray(frame.depth) > 0
                newly = int((static & ~inst.static_mask & valid).sum())  # static: the mask before the check
                if newly > RETRACK_FRACTION * max(1, int(valid.sum())):
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
            t1 = time.perf_counter()
            masked = refresh_keyframes(self.slam.keyframes, self.mm)
            t_keyframes = (time.perf_counter() - t1) * 1e3
            rec["keyframe_rays_masked"] = masked
            rec["retracked"] = retracked
            self.records.append(rec)
        # The map and the backend's keyframe take the mask the frame was classified with before its check, not the
        # one the check left: the check's verdict reaches this keyframe at the next classifier update (forget.
        # refresh_keyframes) and every later frame's mask.  Mapping with the check's mask, or with what both call
        # static, was measured worse on synth `tracking` at 5 and 4 run seeds of 5 (docs/experiments.md).  Unlike
        # tracking, the map (and the written mask) also leaves out a mover's outline where, at the tracked pose, it
        # stands in space the last keyframes saw empty (MotionModule.bound_outline).
        if inst is not None:
            static = self.mm.bound_outline(inst, frame.depth, tr.pose_c2w, self.slam.keyframes, static, dyn_before)
        n_kf = len(self.slam.keyframes)
        mr = self.slam.map(frame, static, None if inst is None else inst.ids)
        row["events"] = this_frames_events(self.slam.events, row["frame"])
        self.frame_rows.append(row)
        if inst is None:
            return {**dict.fromkeys(TIMED, 0.0), "track": t_track, "map": 0.0 if mr is None else mr.ms,
                    "frame": (time.perf_counter() - t0) * 1e3, "_loss": tr.loss}
        t1 = time.perf_counter()
        if len(self.slam.keyframes) > n_kf:
            kf = self.slam.keyframes[-1]
            kf.near_ids = near_ids(inst.mask_ids, kf.pixels, self.mm.m.mask_dilation)
            self.slam.keyframes.register_instances(kf.frame_id, *self.mm.keyframe_instances(inst))
        fid = self.slam.n_frames - 1
        if self.slam.keyframes.landmark_keyframes.index_of(fid) >= 0 and not self.slam.keyframes.has_instances(fid):
            # a backend keyframe without neural-map rays: its landmarks carry these instance ids
            self.slam.keyframes.register_instances(fid, *self.mm.keyframe_instances(inst))
        t_keyframes += (time.perf_counter() - t1) * 1e3
        dyn_mask = inst.dynamic_mask()
        self.last_masks = dyn_mask
        row.update(retracked=retracked, checked=bool(checked), dynamic_instances=int(inst.dynamic.sum()),
                   dynamic_pixels=round(float(dyn_mask.mean()), 6))
        if self.mask_dir is not None:
            self._write_png(self.mask_dir / f"{stamp}.png", dyn_mask.astype(np.uint8) * 255)
        tm = inst.timings
        return {
            "segment": tm.get("segment", 0.0), "encode": tm.get("encode", 0.0),
            "classify": tm.get("classify", 0.0), "track": t_track, "render": t_render,
            "check": tm.get("check", 0.0), "update": tm.get("update", 0.0), "judge": t_judge,
            "keyframes": t_keyframes, "map": 0.0 if mr is None else mr.ms, "wait": 0.0, "frame": (time.perf_counter() - t0) * 1e3,
            "_loss": tr.loss, "_dynamic": int(inst.dynamic.sum()), "_updated": record is not None,
            "_retracked": retracked,
        }

    # ------------------------------------------------------------------ outputs and state
    def mesh(self, voxel: float):
        """The map's mesh at ``voxel`` size and how many of its vertices were left out: in dynamic mode with
        departed surfaces forgotten (``run.forget_radius`` > 0), the surfaces the newest keyframe looking at them
        saw through (:func:`~dynslam_cli.motion.forget.departed_surface`) by more than the map's truncation, or,
        within the check's threshold t_d of a place where the check saw something leave (below t_d it cannot
        see a departure), by more than ``run.forget_radius`` (at most the truncation)."""
        mesh = self.slam.extract_mesh(voxel)
        if self.mm is None or self.forget_radius <= 0 or not len(mesh.vertices):
            return mesh, 0
        verts = np.asarray(mesh.vertices)
        tr = self.slam.model.truncation
        margin = np.where(self.departed.near(verts, self.mm.m.depth_threshold), min(self.forget_radius, tr), tr)
        drop = departed_surface(verts, self.slam.keyframes, self.slam.intr, margin)
        return drop_vertices(mesh, drop), int(drop.sum())

    @staticmethod
    def _write_png(path: Path, image: np.ndarray) -> None:
        import cv2

        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), image):
                raise OSError(f"cannot write {path}")

    def write_updates(self, path: Path) -> Path:
        return write_jsonl_atomic(path, self.records)

    def write_frames(self, path: Path) -> Path:
        """frames.jsonl: one line per frame, how it was tracked (the backend's reason and static inliers, this
        frame's tracking events) and, in dynamic mode, whether it was checked and re-tracked and what it masked."""
        return write_jsonl_atomic(path, self.frame_rows)

    def state_dict(self) -> dict:
        return {"motion": None if self.mm is None else self.mm.state_dict(), "records": list(self.records),
                "frames": list(self.frame_rows), "departed": self.departed.state()}

    def load_state_dict(self, d: dict) -> None:
        if self.mm is not None:
            self.mm.load_state_dict(d["motion"])
        self.records = list(d["records"])
        self.frame_rows = list(d.get("frames", []))  # a checkpoint from before frames.jsonl: the rows from here on
        self.departed.load(d.get("departed", ()))  # from before the departed places: those from here on
