"""When a tracked frame becomes a keyframe: by overlap with the reference keyframe (ORB-SLAM2's
rule for RGB-D), or when too few of its close keypoints are tracked, or after a maximum gap."""

from __future__ import annotations


def need_keyframe(inliers: int, ref_tracked: int, since_last: int, untracked_depth: int, n_keyframes: int,
                  ratio: float, max_gap: int) -> tuple[bool, str]:
    """``inliers``: landmarks the frame tracked; ``ref_tracked``: landmarks of the reference
    keyframe observed by at least two keyframes (one while there is one keyframe);
    ``since_last``: frames since the last keyframe; ``untracked_depth``: the frame's keypoints
    with depth that matched no landmark.  Returns (new keyframe?, why)."""
    if n_keyframes == 0:
        return True, "first"
    th = ratio if n_keyframes >= 2 else 0.4  # ORB-SLAM2: 0.4 while the map has one keyframe
    if inliers < th * ref_tracked and inliers > 15:
        return True, f"overlap {inliers}/{ref_tracked} < {th:g}"
    if inliers < 100 and untracked_depth > 70:  # few tracked close points, many new ones
        return True, f"few tracked ({inliers}), {untracked_depth} new points with depth"
    if since_last >= max_gap:
        return True, f"gap {since_last} frames"
    return False, ""
