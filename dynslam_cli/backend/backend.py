"""`Backend`: ORB-SLAM2-style RGB-D tracking and local mapping on static pixels.

Per frame: ORB keypoints on static pixels → the motion model's guess (``motion.MotionFilter``) →
match the local map (the landmarks of the reference keyframe's covisible keyframes, and of the
keyframes whose landmarks the guess would see again: ``LandmarkKeyframes.in_view``) → robust
pose-only optimisation (wider search, then PnP relocalisation, else ``lost``) → the pose fused with
the motion model's prediction → keyframe decision by overlap → on a keyframe:
its observations, new landmarks from its unmatched keypoints with depth, culling, and local bundle
adjustment of the newest keyframes' window (gtsam).  The keyframes, their poses and the landmarks
are a :class:`~dynslam_cli.backend.keyframes.LandmarkKeyframes` (``keyframes``): the run's keyframe
store hands its own to the backend, so that forgetting reaches the landmarks through the store.

With ``track(..., defer=True)`` the keyframe is inserted by :meth:`Backend.commit`, which takes the
frame's final static mask (the motion check after tracking may have found more movers) and instance
ids: no landmark is made on a pixel known to move by then, and each landmark remembers the instance
it was made on, so :meth:`LandmarkKeyframes.forget` leaves out the landmarks of an instance found to
move later (and takes them back if it is called static again)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from dynslam_cli.backend.bundle import local_bundle_adjustment
from dynslam_cli.backend.config import BackendConfig
from dynslam_cli.backend.features import Detector, Keypoints, backproject, on_depth_discontinuity
from dynslam_cli.backend.keyframes import LandmarkKeyframes, need_keyframe
from dynslam_cli.backend.landmarks import LandmarkMap
from dynslam_cli.backend.motion import MotionFilter
from dynslam_cli.backend.refine import FrameMatches, refine_poses
from dynslam_cli.backend.tracking import Camera, pose_covariance, reprojects_within, track_frame
from dynslam_cli.geometry.camera import pixel_index


@dataclass
class TrackOutcome:
    """The frame's ``pose_c2w`` (4×4; the constant-velocity pose when ``lost``), its static
    ``inliers``, ``lost``, ``keyframe`` (inserted, local BA has run), ``reason`` (how it was
    tracked: motion | wide | relocalised | first | lost: why), ``track_ms``/``ba_ms``, and
    ``landmarks`` (alive after this frame)."""

    pose_c2w: np.ndarray
    inliers: int
    lost: bool
    keyframe: bool
    reason: str
    track_ms: float = 0.0
    ba_ms: float = 0.0
    landmarks: int = 0


class Backend:
    """``intrinsics``: (fx, fy, cx, cy, W, H) of the undistorted images; ``cfg``: BackendConfig;
    ``first_pose``: the first frame's camera-to-world pose (identity when None); ``depth_noise``: the
    sensor's depth noise per metre² (``Sequence.depth_noise``; ``DataConfig.DEPTH_NOISE`` when None);
    ``keyframes``: where the keyframes and landmarks go (the keyframe store's; a new one when None)."""

    def __init__(self, intrinsics, cfg: Optional[BackendConfig] = None, first_pose: Optional[np.ndarray] = None,
                 depth_noise: Optional[float] = None, keyframes: Optional[LandmarkKeyframes] = None):
        fx, fy, cx, cy, w, h = intrinsics
        self.cfg = cfg or BackendConfig()
        self.cam = Camera(float(fx), float(fy), float(cx), float(cy), int(w), int(h), float(fx) * self.cfg.BASELINE)
        if depth_noise is None:
            from dynslam_cli.data.config import DataConfig

            depth_noise = DataConfig.DEPTH_NOISE
        self.detector = Detector(self.cfg.features, int(w), int(h), depth_noise=float(depth_noise))
        self.first_pose = np.eye(4) if first_pose is None else np.asarray(first_pose, np.float64).copy()
        self.keyframes = LandmarkKeyframes() if keyframes is None else keyframes
        self.ref_kf = -1
        self.matches = FrameMatches()  # each tracked frame's matches, for refined_trajectory
        self.last_pose: Optional[np.ndarray] = None
        self.prev_pose: Optional[np.ndarray] = None
        self.last_kf_index = -1
        self.lost_run = 0
        self.motion = MotionFilter()
        self.frame_ref = np.zeros(0, np.int64)  # per tracked frame: its reference keyframe (-1 = none)
        self.frame_rel = np.zeros((0, 4, 4))  # ... and its pose relative to it (absolute when none)
        # frame_ref/frame_rel are the filled rows of these (capacity doubles: appending is amortised O(1))
        self._ref_buf, self._rel_buf = self.frame_ref, self.frame_rel
        self._pending: Optional[tuple] = None  # (index, pose, keypoints, landmark ids, keypoint rows) of a due keyframe
        self._last: Optional[tuple] = None  # (index, guess, keypoints, local-map ids) of the last tracked frame
        self._evidence: Optional[tuple] = None  # its matched keypoints, whether each reprojects, its depth

    @property
    def lm(self) -> LandmarkMap:
        """The landmarks (the keyframes')."""
        return self.keyframes.landmarks

    @property
    def kf_frame(self) -> np.ndarray:
        """Frame index of each keyframe (read-only)."""
        return self.keyframes.frames

    @property
    def kf_pose(self) -> np.ndarray:
        """Each keyframe's bundle-adjusted camera-to-world pose (read-only)."""
        return self.keyframes.poses

    # -- public ------------------------------------------------------------------------------------
    def track(self, index: int, rgb: np.ndarray, depth: np.ndarray, static_mask: Optional[np.ndarray] = None,
              defer: bool = False, stamp: Optional[float] = None) -> TrackOutcome:
        """Track frame ``index`` (RGB H×W×3 uint8, depth H×W metres with 0 = none, ``static_mask``
        H×W bool: True where the pixel may be used; None = all; ``stamp``: its time in seconds, for
        the motion model; None = frames 1/30 s apart).  ``keyframe`` in the outcome: the frame
        became a keyframe (local BA ran) or, with ``defer``, is due to become one at
        :meth:`commit`."""
        t0 = time.perf_counter()
        self._pending = None
        self._last = None
        self._evidence = None
        self.matches.remap(self.lm.compact())  # the frames' matches are the only ids held outside the map
        kp = self.detector.detect(rgb, depth, static_mask)
        n_depth = int((kp.depth > 0).sum())
        if self.last_pose is None:
            self.motion.restart(stamp)
        if len(self.kf_frame) == 0:
            # the first keyframe: at the first pose, or where the caller's corrections of the frames
            # tracked without it (correct_last) put the camera
            start = self.first_pose.copy() if self.last_pose is None else self._predict()
            self._advance(start)
            if n_depth < 2 * self.cfg.min_matches:
                return self._out(start, 0, True, False,
                                 f"lost: not initialised ({n_depth} static keypoints with depth)", t0)
            out = self._out(start, n_depth, False, True, "first", t0)
            self._pending = (int(index), start.copy(), kp, np.zeros(0, np.int64), np.zeros(0, np.int64))
            if not defer:
                self.commit()
            return out
        guess = self.motion.predict(self.last_pose, stamp)
        window = self._local_keyframes(2 * self.cfg.window)
        # and the keyframes of a place seen before that the guess looks at again (not covisible with the newer ones)
        again = self.keyframes.in_view(guess, self.cam.K, self.cam.width, self.cam.height, self.cfg.window,
                                       self.cfg.min_matches, exclude=window)
        ids = self.lm.seen_by(window + again)
        tr = track_frame(self.cam, guess, kp, ids, self.lm.pos[ids], self.lm.des[ids],
                         lambda rows, dist: self.lm.expected_scale(ids[rows], dist), self.cfg.SEARCH_PX,
                         self.cfg.huber_px, self.cfg.min_matches, seed=index)
        if tr.lost:
            self.lost_run += 1
            self._advance(guess)
            if self.lost_run >= self.cfg.KEYFRAME_MAX_GAP and n_depth >= 2 * self.cfg.min_matches:
                # lost for long: start a fresh local map at the predicted pose rather than never recover
                t1 = time.perf_counter()
                self._insert_keyframe(index, guess, kp, np.zeros(0, np.int64), np.zeros(0, np.int64))
                self.lost_run = 0
                self.motion.restart()
                return self._out(guess, 0, True, True, tr.reason + "; new keyframe at the predicted pose", t0,
                                 ba_ms=(time.perf_counter() - t1) * 1000)
            return self._out(guess, 0, True, False, tr.reason, t0)
        self.lost_run = 0
        self._last = (int(index), guess, kp, ids)
        in_window = np.isin(tr.matched_lm, self.lm.seen_by(window)) if again else np.ones(len(tr.matched_lm), bool)
        X = self.lm.pos[tr.matched_lm] if again else None  # where the matched landmarks were, for the window's pose
        self._evidence = (kp.subset(tr.matched), tr.reprojects, depth, in_window, tr.pose, X)  # judged on demand
        pose = self._fuse(tr, kp)
        self.lm.count(tr.visible, tr.lm)
        self.ref_kf = int(self.lm.covisible(tr.lm)[0][0])
        n_obs = self.lm.n_obs()
        ref_ids = self.lm.seen_by([self.ref_kf])
        n_kf = len(self.kf_frame)
        ref_tracked = int((n_obs[ref_ids] >= (2 if n_kf > 1 else 1)).sum())
        untracked = np.ones(len(kp), bool)
        untracked[tr.kp] = False
        new_kf, why = need_keyframe(len(tr.lm), ref_tracked, index - self.last_kf_index,
                                    int((untracked & (kp.depth > 0)).sum()), n_kf, self.cfg.keyframe_ratio,
                                    self.cfg.KEYFRAME_MAX_GAP)
        self._advance(pose)
        reason = tr.reason + (f"; keyframe ({why})" if new_kf else "")
        out = self._out(pose, len(tr.lm), False, new_kf, reason, t0)
        self.matches.set(len(self.frame_ref) - 1, tr.lm, kp.subset(tr.kp))  # for refined_trajectory
        if new_kf:
            self._pending = (int(index), pose.copy(), kp, tr.lm, tr.kp)
            if not defer:
                inserted, ba_ms, pose = self.commit()
                out.pose_c2w, out.ba_ms = pose, ba_ms
        return out

    def reprojection_evidence(self) -> Optional[tuple[np.ndarray, np.ndarray]]:
        """The last tracked frame's matched keypoints (N×2 pixels) and whether each reprojects at its
        tracked pose (:func:`~dynslam_cli.backend.tracking.reprojects`); None where the frame was
        not tracked against the local map (the first frame, a lost frame).  Left out: keypoints on
        occluding contours (:func:`~dynslam_cli.backend.features.on_depth_discontinuity`: their
        corners slide as the camera moves) and matches to landmarks that only the keyframes of a
        place seen again observed (``LandmarkKeyframes.in_view``, none of the covisible window): the
        drift the camera gathered since it was there moves them off their keypoints all together,
        without anything having moved; the tracked pose, pulled between the two, is not the
        window's either, so then the window's matches are judged at the pose they alone give
        (:func:`~dynslam_cli.backend.tracking.reprojects_within`).  Computed when asked (static mode never asks)."""
        if self._evidence is None:
            return None
        matched, ok, depth, in_window, pose, X = self._evidence
        if X is not None:  # a place seen again: the window's matches at the pose they alone give
            ok = reprojects_within(self.cam, pose, X, matched, in_window, self.cfg.huber_px, self.cfg.min_matches)
        v, u = pixel_index(matched.uv, *np.shape(depth))
        keep = ~on_depth_discontinuity(depth, v, u, matched.octave) & in_window
        return matched.uv[keep], ok[keep]

    def retrack(self, static_mask: np.ndarray) -> Optional[np.ndarray]:
        """Track the last frame again from the same prediction on the keypoints that ``static_mask``
        (H×W bool) still calls static: the motion check after tracking found more movers, whose
        keypoints may have pulled the pose.  Its pose (and a due keyframe's) is replaced; returns
        it, or None where nothing changes (no keypoint dropped, the first frame, a lost frame, or
        too few static matches left: the first pose stands)."""
        if self._last is None:
            return None
        index, guess, kp, ids = self._last
        keep = np.asarray(static_mask, bool)[pixel_index(kp.uv, *static_mask.shape)]
        if keep.all():
            return None
        kp = kp.subset(keep)
        tr = track_frame(self.cam, guess, kp, ids, self.lm.pos[ids], self.lm.des[ids],
                         lambda rows, dist: self.lm.expected_scale(ids[rows], dist), self.cfg.SEARCH_PX,
                         self.cfg.huber_px, self.cfg.min_matches, seed=index)
        if tr.lost:
            return None
        pose = self._fuse(tr, kp, redo=True)
        self.correct_last(pose)
        self.matches.set(len(self.frame_ref) - 1, tr.lm, kp.subset(tr.kp))
        if self._pending is not None and self._pending[0] == index:
            self._pending = (index, pose.copy(), kp, tr.lm, tr.kp)
        return pose.copy()

    def commit(self, static_mask: Optional[np.ndarray] = None, instance_ids: Optional[np.ndarray] = None
               ) -> tuple[bool, float, Optional[np.ndarray]]:
        """Insert the keyframe the last :meth:`track` found due, without its keypoints on pixels
        that ``static_mask`` (H×W bool, None = keep all) no longer calls static; ``instance_ids``
        (H×W int) tags its new landmarks for :meth:`forget`.  Returns (inserted, BA ms, the
        frame's bundle-adjusted pose or None)."""
        if self._pending is None:
            return False, 0.0, None
        index, pose, kp, lm_ids, kp_rows = self._pending
        self._pending = None
        t1 = time.perf_counter()
        keep = np.ones(len(kp), bool)
        if static_mask is not None and len(kp):
            keep = np.asarray(static_mask, bool)[pixel_index(kp.uv, *static_mask.shape)]
        origin = None
        if instance_ids is not None and len(kp):
            origin = np.asarray(instance_ids)[pixel_index(kp.uv, *instance_ids.shape)].astype(np.int64)
        pair = keep[kp_rows] if len(kp_rows) else np.zeros(0, bool)
        rows = np.flatnonzero(keep)
        remap = np.full(len(kp), -1, np.int64)
        remap[rows] = np.arange(len(rows))
        kept_kp = kp.subset(rows)
        refined = self._insert_keyframe(index, pose, kept_kp, lm_ids[pair], remap[kp_rows[pair]],
                                        None if origin is None else origin[rows])
        kf = len(self.kf_frame) - 1
        self.frame_ref[-1] = kf  # the frame now stands on its own keyframe
        self.matches.drop(len(self.frame_ref) - 1)  # its pose is bundle adjustment's
        self.frame_rel[-1] = np.eye(4)
        self.last_pose = refined.copy()
        return True, (time.perf_counter() - t1) * 1000, refined.copy()

    def correct_last(self, pose_c2w: np.ndarray) -> None:
        """Replace the last tracked frame's pose (a lost frame that the caller tracked otherwise);
        the motion model continues from it."""
        if len(self.frame_ref) == 0:
            return
        ref = int(self.frame_ref[-1])
        pose = np.asarray(pose_c2w, np.float64)
        self.frame_rel[-1] = pose if ref < 0 else np.linalg.inv(self.kf_pose[ref]) @ pose
        self.last_pose = pose.copy()

    def trajectory(self) -> np.ndarray:
        """Every tracked frame's camera-to-world pose (F×4×4), each composed with its reference
        keyframe's current pose (so bundle adjustment moves the frames between keyframes too)."""
        out = self.frame_rel.copy()
        has = self.frame_ref >= 0
        out[has] = self.kf_pose[self.frame_ref[has]] @ self.frame_rel[has]
        return out

    def finish(self):
        """After the last frame: all keyframes bundle-adjusted together (:meth:`LandmarkKeyframes.adjust_all`)."""
        return self.keyframes.adjust_all(self.cam, self.cfg.huber_px)

    def refined_trajectory(self) -> tuple[np.ndarray, int]:
        """:meth:`trajectory` with every frame but the keyframes solved again against the finished
        map (:func:`~dynslam_cli.backend.refine.refine_poses`), and how many were solved again."""
        usable = self.lm.alive & ~self.lm.moving
        return refine_poses(self.cam, self.trajectory(), self.matches, self.lm.pos, usable, self.cfg.min_matches,
                            self.cfg.huber_px)

    def keyframe_poses(self) -> dict:
        """Frame index → the keyframe's current (bundle-adjusted) camera-to-world pose."""
        return {int(f): p.copy() for f, p in zip(self.kf_frame, self.kf_pose, strict=False)}

    def state_dict(self) -> dict:
        """Everything besides the keyframes (``keyframes.state_dict()``, which the keyframe store
        saves) needed to continue identically (numpy arrays only)."""
        nan = np.full((4, 4), np.nan)
        d = {"ref_kf": np.array(self.ref_kf), "last_kf_index": np.array(self.last_kf_index),
             "lost_run": np.array(self.lost_run), "first_pose": self.first_pose.copy(),
             "frame_ref": self.frame_ref.copy(), "frame_rel": self.frame_rel.copy(),
             "last_pose": nan if self.last_pose is None else self.last_pose.copy(),
             "prev_pose": nan if self.prev_pose is None else self.prev_pose.copy()}
        d.update({f"motion.{k}": v for k, v in self.motion.state_dict().items()})
        d.update({f"matches.{k}": v for k, v in self.matches.state_dict().items()})
        return d

    def load_state_dict(self, d: dict) -> None:
        self.ref_kf = int(d["ref_kf"])
        self.last_kf_index = int(d["last_kf_index"])
        self.lost_run = int(d["lost_run"])
        self.first_pose = np.array(d["first_pose"], np.float64)
        self.frame_ref = self._ref_buf = np.array(d["frame_ref"], np.int64)
        self.frame_rel = self._rel_buf = np.array(d["frame_rel"], np.float64).reshape(-1, 4, 4)
        last, prev = np.array(d["last_pose"], np.float64), np.array(d["prev_pose"], np.float64)
        self.last_pose = None if np.isnan(last).any() else last
        self.prev_pose = None if np.isnan(prev).any() else prev
        motion = {k[7:]: v for k, v in d.items() if k.startswith("motion.")}
        if motion:  # a checkpoint from before the motion model: it starts afresh
            self.motion.load_state_dict(motion)
        matches = {k[8:]: v for k, v in d.items() if k.startswith("matches.")}
        self.matches = FrameMatches()  # a checkpoint from before: only the frames after it are refined
        if matches:
            self.matches.load_state_dict(matches)

    # -- internals ---------------------------------------------------------------------------------
    def _fuse(self, tr, kp: Keypoints, redo: bool = False) -> np.ndarray:
        """The tracked pose fused with the motion model's prediction (a relocalised frame: the
        tracked pose, and the motion is learnt afresh)."""
        if tr.reason == "relocalised":
            self.motion.restart()
            return tr.pose.copy()
        cov = pose_covariance(self.cam, tr.pose, self.lm.pos[tr.lm], kp.subset(tr.kp))
        return self.motion.update(tr.pose, cov, redo=redo)

    def _out(self, pose, inliers, lost, kf, reason, t0, ba_ms=0.0) -> TrackOutcome:
        ref = self.ref_kf if len(self.kf_frame) else -1
        rel = pose if ref < 0 else np.linalg.inv(self.kf_pose[ref]) @ pose
        self._append_frame(ref, rel)
        ms = (time.perf_counter() - t0) * 1000 - ba_ms
        return TrackOutcome(pose, int(inliers), bool(lost), bool(kf), reason, ms, ba_ms, self.lm.n_alive)

    def _append_frame(self, ref: int, rel: np.ndarray) -> None:
        """A tracked frame's row in frame_ref/frame_rel (views of the buffers, grown by doubling)."""
        n = len(self.frame_ref)
        if n == len(self._ref_buf):
            cap = max(64, 2 * n)
            ref_buf, rel_buf = np.empty(cap, np.int64), np.empty((cap, 4, 4))
            ref_buf[:n], rel_buf[:n] = self.frame_ref, self.frame_rel
            self._ref_buf, self._rel_buf = ref_buf, rel_buf
        self._ref_buf[n], self._rel_buf[n] = ref, rel
        self.frame_ref, self.frame_rel = self._ref_buf[:n + 1], self._rel_buf[:n + 1]

    def _predict(self) -> np.ndarray:
        """Constant velocity: the last frame-to-frame motion (in the camera frame) once more."""
        if self.prev_pose is None:
            return self.last_pose.copy()
        return self.last_pose @ (np.linalg.inv(self.prev_pose) @ self.last_pose)

    def _advance(self, pose: np.ndarray) -> None:
        self.prev_pose, self.last_pose = self.last_pose, pose.copy()

    def _local_keyframes(self, n: int, kf: Optional[int] = None) -> list[int]:
        """Keyframe ``kf`` (the reference) and the ``n - 1`` keyframes sharing most landmarks with it."""
        kf = self.ref_kf if kf is None else kf
        kfs, _ = self.lm.covisible(self.lm.seen_by([kf]))
        out = [kf] + [int(k) for k in kfs if k != kf]
        return out[:n]

    def _insert_keyframe(self, index: int, pose: np.ndarray, kp: Keypoints, lm_ids: np.ndarray,
                         kp_rows: np.ndarray, origin: Optional[np.ndarray] = None) -> np.ndarray:
        """New keyframe: observations of the tracked landmarks, landmarks from the keypoints with
        depth that matched none, culling, local bundle adjustment.  Returns its refined pose."""
        kf = self.keyframes.add(index, pose)
        self.last_kf_index = int(index)
        if len(lm_ids):
            self.lm.observe(kf, lm_ids, kp.subset(kp_rows))
        fresh = np.ones(len(kp), bool)
        fresh[kp_rows] = False
        fresh &= kp.depth > 0
        new = kp.subset(fresh)
        self.lm.create(kf, new, backproject(new, self.cam.K, pose), pose[:3, 3],
                       None if origin is None else origin[fresh])
        self.ref_kf = kf
        if kf == 0:
            return pose
        self.lm.cull_recent(kf)
        local = self._local_keyframes(self.cfg.window, kf)
        ids = self.lm.seen_by(local)
        if len(ids) == 0:
            return pose
        observers = np.unique(self.lm.obs_kf[np.isin(self.lm.obs_lm, ids)])
        fixed = [int(k) for k in observers if int(k) not in local]
        optimise = [k for k in local if k != 0]
        fixed += [0] if 0 in local else []
        poses = {int(k): self.kf_pose[k] for k in set(optimise) | set(fixed)}
        res = local_bundle_adjustment(self.cam, poses, optimise, fixed, ids, self.lm.pos[ids], self.lm.obs_kf,
                                      self.lm.obs_lm, self.lm.obs_uv, self.lm.obs_depth, self.lm.obs_octave, self.lm.obs_dsig,
                                      self.cfg.huber_px)
        for k, T in res.poses.items():
            self.keyframes.set_pose(k, T)
        self.lm.pos[res.ids] = res.pos
        self.lm.drop_observations(res.outlier)
        return self.kf_pose[kf].copy()
