"""The bidirectional inconsistency check between observed and rendered depth (paper Eq. 8-9).

Forward: instance k is observed moving when the fraction of its valid pixels with
rendered − observed > t_d exceeds t_p (something now stands in front of the map).
Backward: the rendered view is segmented (geometric segmenter on rendered rgb + depth); a rendered
segment is flagged when observed − rendered > t_d on more than t_p of its valid pixels (the mapped
thing left or moved away); the caller encodes flagged rendered segments and labels them dynamic.
Optionally (``backward_current``) they are also mapped onto the current instances by overlap:
instance k is then observed moving when the 'behind' pixels inside flagged rendered segments make
up more than t_p of its valid pixels (that labels the uncovered background, so it is off by
default). Everything runs at a reduced resolution.
"""

from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from dynslam_cli.motion.types import CheckResult


def _resize(a: np.ndarray, wh: tuple[int, int], nearest: bool = True) -> np.ndarray:
    if a.shape[1::-1] == wh:
        return a
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    if a.dtype in (np.int32, np.int64):
        return cv2.resize(a.astype(np.float32), wh, interpolation=cv2.INTER_NEAREST).astype(np.int32)
    return cv2.resize(a, wh, interpolation=interp)


def check_size(h: int, w: int, width: int) -> tuple[int, int]:
    s = min(1.0, width / w)
    return max(1, int(round(w * s))), max(1, int(round(h * s)))


def inconsistency_check(observed_depth: np.ndarray, rendered_depth: np.ndarray, ids: np.ndarray,
                        t_d: float = 0.3, t_p: float = 0.05, rendered_rgb: Optional[np.ndarray] = None,
                        rendered_segmenter=None, width: int = 160, min_pixels: int = 12,
                        forward_valid: Optional[np.ndarray] = None, backward_current: bool = False) -> CheckResult:
    """Run the check. ``observed_depth`` and ``ids`` at frame resolution, ``rendered_*`` any size.

    ``forward_valid`` (frame resolution, bool): pixels where "observed in front of the map" may
    count (e.g. space some keyframe observed); None = everywhere valid.

    ``backward_current``: also mark current instances as moving from the 'behind' pixels inside
    flagged rendered segments.  Off by default: those pixels show what the departed object
    uncovered (the floor or wall behind it), which is static; the object that left is the flagged
    rendered segment itself (``rendered_flagged``), which callers label dynamic."""
    H, W = observed_depth.shape[:2]
    wh = check_size(H, W, width)
    obs = _resize(np.nan_to_num(observed_depth.astype(np.float32)), wh)
    ren = _resize(np.nan_to_num(rendered_depth.astype(np.float32)), wh)
    idm = _resize(ids.astype(np.int32), wh)
    k = int(ids.max(initial=0))
    valid = (obs > 0) & (ren > 0)
    fwd_px = valid & (ren - obs > t_d)
    if forward_valid is not None:
        fwd_px &= _resize(np.asarray(forward_valid).astype(np.uint8), wh) > 0
    bwd_px = valid & (obs - ren > t_d)
    n_valid = np.bincount(idm[valid], minlength=k + 1)[: k + 1]
    n_fwd = np.bincount(idm[fwd_px], minlength=k + 1)[: k + 1]
    frac = n_fwd / np.maximum(n_valid, 1)
    judged = n_valid >= min_pixels
    fwd = judged & (frac > t_p)
    bwd = np.zeros(k + 1, bool)
    rendered_ids = None
    flagged = np.zeros(0, np.int64)
    if rendered_segmenter is not None and bwd_px.any():
        rgb_small = None
        if rendered_rgb is not None:
            rgb = rendered_rgb
            if rgb.dtype != np.uint8:
                rgb = np.clip(rgb * (255.0 if rgb.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
            rgb_small = cv2.resize(rgb, wh, interpolation=cv2.INTER_AREA) if rgb.shape[1::-1] != wh else rgb
        seg = rendered_segmenter.segment(rgb_small, ren)
        rendered_ids = seg.ids
        kr = int(rendered_ids.max(initial=0))
        rv = np.bincount(rendered_ids[valid], minlength=kr + 1)[: kr + 1]
        rb = np.bincount(rendered_ids[bwd_px], minlength=kr + 1)[: kr + 1]
        rflag = (rv >= min_pixels) & (rb / np.maximum(rv, 1) > t_p)
        rflag[0] = False
        flagged = np.nonzero(rflag)[0]
        if len(flagged) and backward_current:
            in_flagged = rflag[rendered_ids] & bwd_px
            n_b = np.bincount(idm[in_flagged], minlength=k + 1)[: k + 1]
            bwd = judged & (n_b / np.maximum(n_valid, 1) > t_p)
    moving = fwd | bwd
    return CheckResult(
        observed_moving=moving[1:], forward=fwd[1:], backward=bwd[1:], fractions=frac[1:].astype(np.float32),
        background_forward=float(frac[0]), background_moving=bool(moving[0]),
        rendered_ids=rendered_ids, rendered_flagged=flagged, judged=judged[1:],
    )

