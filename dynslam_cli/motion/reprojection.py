"""Sparse evidence that an instance moved: its keypoints stopped reprojecting.

The inconsistency check (:mod:`.check`) sees an instance move once its surface is ``t_d`` (0.3 m)
off the map.  The keyframe backend sees it sooner: landmarks made on a thing that was still, when
it starts to move, stop reprojecting onto their keypoints at the pose the rest of the frame gives.
:func:`moving_by_reprojection` turns the backend's per-match verdicts
(:meth:`~dynslam_cli.backend.backend.Backend.reprojection_evidence`) into a per-instance vote with
a one-sided binomial test: an instance moved when more of its matches fail to reproject than the
frame's own failure rate makes plausible at significance :data:`ALPHA`.
"""

from __future__ import annotations

import numpy as np

from dynslam_cli.geometry.camera import pixel_index

# One-sided significance of "this instance's matches fail more often than the frame's": at most about one false vote
# in a thousand instance tests where nothing moved.
ALPHA = 1e-3
# The failure rate assumed at least: the reprojection gate is the 95 % chi-square gate, so 5 % of the matches of a
# still scene fail it by chance.
GATE_FALSE_ALARM = 0.05


def moving_by_reprojection(ids: np.ndarray, uv: np.ndarray, ok: np.ndarray, count: int) -> np.ndarray:
    """Per instance (ids 1..``count`` of the H×W ``ids``; 0 is no instance), whether its matched
    keypoints (pixels ``uv`` N×2, ``ok``: whether each reprojects) fail significantly more often
    than the frame's rate, max(failures / matches, :data:`GATE_FALSE_ALARM`): the binomial
    probability of at least that many failures among the instance's matches is below :data:`ALPHA`.
    (count,) bool; all False without matches."""
    from scipy.special import bdtrc  # binomial upper tail; scipy.stats' binom.sf costs 0.6-1.7 s to import

    out = np.zeros(int(count), bool)
    ok = np.asarray(ok, bool)
    if count <= 0 or len(ok) == 0:
        return out
    v, u = pixel_index(uv, *np.shape(ids))
    inst = np.asarray(ids)[v, u].astype(np.int64)
    rate = max(float((~ok).mean()), GATE_FALSE_ALARM)
    n = np.bincount(inst, minlength=count + 1)[1:count + 1]
    bad = np.bincount(inst, weights=(~ok).astype(np.float64), minlength=count + 1)[1:count + 1].astype(np.int64)
    has = n > 0
    k = bad[has]
    p = np.where(k > 0, bdtrc(np.maximum(k - 1, 0), n[has], rate), 1.0)  # P(X >= k) = P(X > k - 1)
    out[has] = (p < ALPHA) & (bad[has] > rate * n[has])
    return out
