"""What of an observation the map can judge, before the inconsistency check (:mod:`.check`).

:func:`checkable_depth` leaves out depth edges and space no recent keyframe saw, and says where
"observed in front of the map" is evidence of motion (:func:`keyframe_visibility`);
:func:`closest_rendered` forgives the map's blurred edges; :func:`bounded_extent` gives a mover the outline pixels
that stand where recent keyframes saw empty space.  :func:`project_into` puts world points
into a keyframe's camera and :func:`depth_cell` finds them in its subsampled depth map (both also used by
:mod:`.stayed` and :mod:`.forget`).
"""

from __future__ import annotations

import numpy as np

from dynslam_cli.geometry.camera import pixel_dirs, project, transform
from dynslam_cli.geometry.lie import inv_np
from dynslam_cli.motion import _instance_kernels as kernels
from dynslam_cli.slam.keyframes import DEPTH_STRIDE, depth_edges

# keyframes whose frusta count as 'observed space' for the check
FRUSTUM_KEYFRAMES = 20
# keyframes whose depth says where something new stands for a mover's outline (:func:`seen_through`): the last
# three, half a second at 30 Hz with a keyframe every 5 frames (docs/experiments.md: the newest alone took less)
SEEN_THROUGH_KEYFRAMES = 3


def project_into(world: np.ndarray, pose_c2w: np.ndarray, intr, W: int, H: int, border: int = 0):
    """World points into a camera: camera-frame points, pixel u, v and whether each lands inside
    the W×H image (less ``border`` pixels on every side) in front of the camera."""
    pc = transform(inv_np(pose_c2w), world)
    uv, z = project(pc, intr.fx, intr.fy, intr.cx, intr.cy)
    u, v = uv[:, 0], uv[:, 1]
    b = max(0, int(border))
    inside = (z > 0.05) & (u >= b) & (u <= W - 1 - b) & (v >= b) & (v <= H - 1 - b)
    return pc, u, v, inside


def depth_cell(u: np.ndarray, v: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """Row and column (int64) of the pixels ``u``, ``v`` in a keyframe's depth map kept every
    :data:`DEPTH_STRIDE` pixels (of ``shape``): the nearest cell, clipped to the map."""
    hs, ws = shape
    iv = np.clip(np.round(v / DEPTH_STRIDE).astype(np.int64), 0, hs - 1)
    iu = np.clip(np.round(u / DEPTH_STRIDE).astype(np.int64), 0, ws - 1)
    return iv, iu


def keyframe_visibility(depth: np.ndarray, pose_c2w: np.ndarray, intr, keyframes, step: int = 4,
                        occlusion_margin: float = 0.3, border: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """What the keyframes saw of the current frame's back-projected points (at ``pose_c2w``).

    Returns two (H, W) bool masks, evaluated every ``step``-th pixel and upsampled (nearest):

    - ``in_frustum``: the point lies inside the view frustum of at least one keyframe, less the
      ``border`` pixels at the edges of its image (the map is never taught from those rays:
      ``tracking.ignore_border``);
    - ``observed``: for at least one keyframe the point is inside its frustum and the keyframe's
      measured depth there (``depth_small``) does not stop more than ``occlusion_margin`` in front
      of it: that keyframe saw the point, or the free space where it now is, not an occluder.
      Keyframes without ``depth_small`` count their whole frustum as observed.

    Both are all False when there are no keyframes.
    """
    import cv2

    d = np.asarray(depth, np.float32)
    H, W = d.shape
    if not keyframes:
        return np.zeros((H, W), bool), np.zeros((H, W), bool)
    vs, us = np.mgrid[0:H:step, 0:W:step]
    z = d[::step, ::step]
    pts = pixel_dirs(us.ravel(), vs.ravel(), intr.fx, intr.fy, intr.cx, intr.cy) * z.reshape(-1, 1)
    world = transform(pose_c2w, pts)
    frustum = np.zeros(len(world), bool)
    observed = np.zeros(len(world), bool)
    # a point some keyframe observed is in that keyframe's frustum too, so both masks are final for it: each keyframe
    # (newest first: they overlap the frame most) projects only the points not observed yet.  Every sample without
    # depth back-projects to the camera centre, one and the same point: the first of them stands for all
    zr = z.ravel()
    none, todo = np.flatnonzero(zr == 0), np.flatnonzero(zr != 0)
    if len(none):
        todo = np.append(todo, none[0])
    for kf in reversed(keyframes):
        if len(todo) == 0:
            break
        pc, u, v, inside = project_into(world[todo], kf.pose_c2w, intr, W, H, border)
        frustum[todo[inside]] = True
        small = kf.depth_small
        if small is not None and inside.any():
            idx = np.flatnonzero(inside)
            iv, iu = depth_cell(u[idx], v[idx], small.shape)
            d_kf = small[iv, iu].astype(np.float32)
            inside[idx[(d_kf <= 0) | (d_kf < pc[idx, 2] - occlusion_margin)]] = False
        observed[todo[inside]] = True
        todo = todo[~inside]
    if len(none):
        frustum[none], observed[none] = frustum[none[0]], observed[none[0]]

    def up(m):
        return cv2.resize(m.reshape(z.shape).astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0

    return up(frustum), up(observed)


def checkable_depth(depth: np.ndarray, pose_c2w: np.ndarray, intr, keyframes, depth_threshold: float,
                    step: int = 4, frustum_keyframes: int = FRUSTUM_KEYFRAMES, border: int = 0):
    """What of the observed depth the map can judge: returns ``(depth, forward_ok)``.

    ``depth`` is the observation with these pixels set to 0 (invalid):

    - pixels within 2 px of a depth discontinuity (relative jump > 5 %), where a one-pixel
      misalignment between the reduced-resolution render and the observation reads as metres;
    - pixels whose 3-D point lies outside the view frustum of every one of the last
      ``frustum_keyframes`` ``keyframes``, less their ``border`` pixels at the image edges (the
      mapper's ``tracking.ignore_border``): space the map was never taught, newly revealed or at
      the edge of every view so far, whose rendered depth means nothing.

    ``forward_ok`` (bool) marks the pixels where "observed in front of the map" is evidence of
    motion: some keyframe saw the point or the free space where it now is, not an occluder in
    front of it (space hidden behind an occluder, more than ``depth_threshold`` behind what the
    keyframe measured, is unknown to the map too).  "Observed behind the map" (a mapped thing
    left) is judged on every valid pixel.
    """
    d = depth.astype(np.float32)
    out = np.where((d > 0) & ~depth_edges(d, 0.05, 2), d, 0.0).astype(np.float32)
    if not keyframes:
        return out, out > 0
    frustum, observed = keyframe_visibility(d, pose_c2w, intr, keyframes[-frustum_keyframes:], step, depth_threshold,
                                            border)
    out[~frustum] = 0.0
    return out, observed


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


def seen_through(depth: np.ndarray, where: np.ndarray, pose_c2w: np.ndarray, intr, keyframes,
                 margin: float, newest: int = SEEN_THROUGH_KEYFRAMES) -> np.ndarray:
    """(H, W) bool: the pixels ``where`` (with depth) whose 3-D point (at ``pose_c2w``) lies in space one of the
    last ``newest`` keyframes saw empty: its whole depth map (``depth_raw_small``, movers included) reads more than
    ``margin`` behind the point where the point lands in its image (a free-space violation: something stands there
    now that was not there then).  Points no such keyframe saw through are False."""
    d = np.asarray(depth, np.float32)
    kfs = [kf for kf in list(keyframes)[-newest:] if kf.depth_raw_small is not None]
    if not kfs:
        return np.zeros(d.shape, bool)
    w2c = np.stack([inv_np(np.asarray(kf.pose_c2w, np.float64)) for kf in kfs])
    small = np.stack([np.asarray(kf.depth_raw_small, np.float32) for kf in kfs])
    return kernels.seen_through(d, np.ascontiguousarray(where, dtype=bool), np.asarray(pose_c2w, np.float64),
                                float(intr.fx), float(intr.fy), float(intr.cx), float(intr.cy), w2c, small,
                                DEPTH_STRIDE, float(margin))


def bounded_extent(ids: np.ndarray, extent: np.ndarray, depth: np.ndarray, pose_c2w: np.ndarray, intr, keyframes,
                   margin: float) -> np.ndarray:
    """The instance ids, with a segmentation's ``extent`` taken only where the observation contradicts what the
    keyframes saw: a pixel the extent gives to another instance than ``ids`` does (an edge band or speck whose depth
    continues that instance) takes the extent's instance where :func:`seen_through` (something new stands there),
    and keeps its id elsewhere.  A static surface beside a mover keeps its own segment; the outline of something
    that moved there goes with it.  Returns ``ids`` itself when nothing changes."""
    where = (extent != ids) & (extent > 0)
    if not where.any():
        return ids
    take = seen_through(depth, where, pose_c2w, intr, keyframes, margin)
    if not take.any():
        return ids
    out = ids.copy()
    out[take] = extent[take]
    return out
