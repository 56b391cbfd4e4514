"""Landmarks: 3-D points in the world frame with an ORB descriptor, created from a keyframe's
keypoints with depth on static pixels; which keyframes observed them (flat observation arrays);
found/visible counts; culling (ORB-SLAM's rules).  Everything is numpy arrays indexed by landmark
id.  Culled landmarks keep their row with ``alive`` false until :meth:`LandmarkMap.compact` drops
the dead rows and renumbers the rest (in order); the owner of the map calls it when no landmark id
is held outside the map (``Backend`` does at the start of each frame)."""

from __future__ import annotations

import numpy as np

from dynslam_cli.backend.features import SCALE, Keypoints

_LM = ("pos", "des", "octave", "dist", "first_kf", "origin", "moving", "visible", "found", "alive")
_OBS = ("obs_kf", "obs_lm", "obs_uv", "obs_depth", "obs_octave", "obs_dsig")
# compact() drops the dead rows once they are more than this fraction of the rows (and the map has at
# least COMPACT_MIN_ROWS): each compaction removes at least half the rows, so its cost is amortised O(1)
# per culled landmark and the rows stay under twice the alive landmarks
COMPACT_DEAD_FRACTION = 0.5
COMPACT_MIN_ROWS = 1024


class LandmarkMap:
    """``pos`` (N×3 world), ``des`` (N×32), ``octave`` and ``dist`` (pyramid level and camera
    distance when created: the scale it is expected at elsewhere), ``first_kf`` (keyframe id that
    created it), ``origin`` (the instance id of the pixel it was created on, -1 = unknown:
    an instance found to move has its landmarks set ``moving``, left out of tracking and bundle
    adjustment until it is called static again), ``visible`` (frames it
    projected into), ``found`` (frames it was matched in as an inlier), ``alive``.  Observations
    (one per keyframe that matched it): ``obs_kf``, ``obs_lm``, ``obs_uv``, ``obs_depth`` (0 = no
    depth), ``obs_octave``."""

    def __init__(self):
        self.pos = np.zeros((0, 3))
        self.des = np.zeros((0, 32), np.uint8)
        self.octave = np.zeros(0, np.int64)
        self.dist = np.zeros(0)
        self.first_kf = np.zeros(0, np.int64)
        self.origin = np.zeros(0, np.int64)
        self.moving = np.zeros(0, bool)
        self.visible = np.zeros(0, np.int64)
        self.found = np.zeros(0, np.int64)
        self.alive = np.zeros(0, bool)
        self.obs_kf = np.zeros(0, np.int64)
        self.obs_lm = np.zeros(0, np.int64)
        self.obs_uv = np.zeros((0, 2))
        self.obs_depth = np.zeros(0)
        self.obs_octave = np.zeros(0, np.int64)
        self.obs_dsig = np.zeros(0)

    def __len__(self) -> int:
        return int(len(self.pos))

    @property
    def n_alive(self) -> int:
        return int(self.alive.sum())

    # -- creation and observations ------------------------------------------------------------
    def create(self, kf: int, kp: Keypoints, X: np.ndarray, cam_centre: np.ndarray,
               origin: np.ndarray | None = None) -> np.ndarray:
        """New landmarks at world points ``X`` from keyframe ``kf``'s keypoints ``kp`` (each with
        depth; ``origin``: the instance id under each, None = unknown); returns their ids.  Each
        starts seen and found once, observed by ``kf``."""
        n = len(kp)
        ids = np.arange(len(self), len(self) + n)
        self.pos = np.concatenate([self.pos, X])
        self.des = np.concatenate([self.des, kp.des])
        self.octave = np.concatenate([self.octave, kp.octave])
        self.dist = np.concatenate([self.dist, np.linalg.norm(X - cam_centre, axis=1)])
        self.first_kf = np.concatenate([self.first_kf, np.full(n, kf, np.int64)])
        org = np.full(n, -1, np.int64) if origin is None else np.asarray(origin, np.int64).reshape(n)
        self.origin = np.concatenate([self.origin, org])
        self.moving = np.concatenate([self.moving, np.zeros(n, bool)])
        self.visible = np.concatenate([self.visible, np.ones(n, np.int64)])
        self.found = np.concatenate([self.found, np.ones(n, np.int64)])
        self.alive = np.concatenate([self.alive, np.ones(n, bool)])
        self.observe(kf, ids, kp)
        return ids

    def observe(self, kf: int, ids: np.ndarray, kp: Keypoints) -> None:
        """Keyframe ``kf`` observed landmarks ``ids`` at keypoints ``kp`` (same order)."""
        self.obs_kf = np.concatenate([self.obs_kf, np.full(len(ids), kf, np.int64)])
        self.obs_lm = np.concatenate([self.obs_lm, np.asarray(ids, np.int64)])
        self.obs_uv = np.concatenate([self.obs_uv, kp.uv])
        self.obs_depth = np.concatenate([self.obs_depth, kp.depth])
        self.obs_octave = np.concatenate([self.obs_octave, kp.octave])
        self.obs_dsig = np.concatenate([self.obs_dsig, kp.dsig])

    def n_obs(self) -> np.ndarray:
        """Keyframes observing each landmark (N)."""
        return np.bincount(self.obs_lm, minlength=len(self))

    def seen_by(self, kfs) -> np.ndarray:
        """Ids of the alive landmarks observed by any keyframe in ``kfs`` (sorted)."""
        ids = np.unique(self.obs_lm[np.isin(self.obs_kf, np.asarray(list(kfs), np.int64))])
        return ids[self.alive[ids] & ~self.moving[ids]]

    def covisible(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Keyframes observing any of landmarks ``ids`` and how many of them each observes, most first
        (ties: newest first)."""
        sel = np.zeros(len(self), bool)
        sel[np.asarray(ids, np.int64)] = True
        kfs, counts = np.unique(self.obs_kf[sel[self.obs_lm]], return_counts=True)
        order = np.lexsort((-kfs, -counts))
        return kfs[order], counts[order]

    # -- counts and culling ----------------------------------------------------------------------
    def count(self, visible: np.ndarray, found: np.ndarray) -> None:
        np.add.at(self.visible, np.asarray(visible, np.int64), 1)
        np.add.at(self.found, np.asarray(found, np.int64), 1)

    def cull_recent(self, current_kf: int, min_ratio: float = 0.25, age: int = 2, min_kfs: int = 2,
                    recent: int = 3) -> int:
        """ORB-SLAM's culling of landmarks created in the last ``recent`` keyframes: found in fewer
        than ``min_ratio`` of the frames they were visible in, or, ``age`` keyframes after
        creation, observed by fewer than ``min_kfs`` keyframes.  Returns how many were culled."""
        since = current_kf - self.first_kf
        young = self.alive & (since < recent)
        ratio = self.found / np.maximum(self.visible, 1)
        bad = young & ((ratio < min_ratio) | ((since >= age) & (self.n_obs() < min_kfs)))
        self.kill(bad)
        return int(bad.sum())

    def drop_observations(self, drop: np.ndarray, min_left: int = 2) -> int:
        """Remove observations (bool over observations; e.g. outliers after bundle adjustment); a
        landmark that lost one and has fewer than ``min_left`` left is culled.  Returns the culled."""
        lost_one = np.zeros(len(self), bool)
        lost_one[self.obs_lm[drop]] = True
        self._keep_obs(~drop)
        bad = self.alive & lost_one & (self.n_obs() < min_left)
        self.kill(bad)
        return int(bad.sum())

    def set_moving(self, kf: int, instance_ids) -> int:
        """The landmarks keyframe ``kf`` created on instances ``instance_ids`` are moving (left out
        of tracking and bundle adjustment); its others are not (an instance called dynamic by
        mistake gets its landmarks back).  Returns how many alive landmarks of ``kf`` are moving."""
        own = (self.first_kf == kf) & (self.origin >= 0)
        self.moving[own] = np.isin(self.origin[own], np.asarray(instance_ids, np.int64))
        return int((self.moving & own & self.alive).sum())

    def kill(self, bad: np.ndarray) -> None:
        self.alive &= ~bad
        self._keep_obs(self.alive[self.obs_lm])

    def compact(self, force: bool = False) -> np.ndarray | None:
        """Drop the dead rows when they are over COMPACT_DEAD_FRACTION of at least COMPACT_MIN_ROWS
        rows (any dead rows with ``force``): the alive landmarks keep their order and get the ids
        0..n_alive-1, observations follow them.  Returns the old id → new id map (-1 for the dropped),
        or None when nothing changed; every landmark id held elsewhere must be mapped through it."""
        n, alive = len(self), self.n_alive
        dead = n - alive
        if dead == 0 or not (force or (n >= COMPACT_MIN_ROWS and dead > COMPACT_DEAD_FRACTION * n)):
            return None
        keep = self.alive.copy()
        remap = np.full(n, -1, np.int64)
        remap[keep] = np.arange(alive)
        for k in _LM:
            setattr(self, k, getattr(self, k)[keep])
        self._keep_obs(keep[self.obs_lm])  # none of a dead landmark's (kill drops them): a no-op
        self.obs_lm = remap[self.obs_lm]
        return remap

    def _keep_obs(self, keep: np.ndarray) -> None:
        for k in _OBS:
            setattr(self, k, getattr(self, k)[keep])

    def expected_scale(self, ids: np.ndarray, dist: np.ndarray) -> np.ndarray:
        """The ORB scale factor a landmark is expected at from camera distance ``dist``."""
        return SCALE ** self.octave[ids] * self.dist[ids] / np.maximum(dist, 1e-6)

    # -- checkpoints ------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {k: getattr(self, k).copy() for k in _LM + _OBS}

    def load_state_dict(self, d: dict) -> None:
        for k in _LM + _OBS:
            setattr(self, k, np.array(d[k], dtype=getattr(self, k).dtype))
