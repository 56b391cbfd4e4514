"""Bonn RGB-D Dynamic (Palazzolo et al., IROS 2019) specifics.

The frames use the TUM layout (read by :mod:`dynslam_cli.data.tum`); intrinsics and distortion
come from ``configs/bonn.yaml``.  Ground truth is the pose of the motion-capture marker body.
To put a camera (or a reconstruction made in the ground-truth frame) into the frame of Bonn's
laser-scanned reference cloud, the dataset's own ``compute_global_transformation.py`` composes

    T_ref = T_ros · T_gt · T_ros · T_m

with the constants below.  ``T_m``'s 3×3 block is not a rotation but a rotation scaled by 1.0593 (every column and
every singular value has that norm): the sensor's depth, read as the PNG value / 5000, is 5.6 % short of the
motion capture's and the laser scan's metres, and ``T_m`` scales the camera-frame points up to them
(:data:`DEPTH_SCALE_FACTOR`).  ``configs/bonn.yaml`` applies that factor where the depth is read
(``data.depth_scale`` = 5000 / 1.0593), so a reconstruction and its trajectory are already in metres and
:func:`rigid_T_m` keeps only the rotation, the nearest in the Frobenius sense, ``U · diag(1, 1, det(U Vᵀ)) · Vᵀ``
from its SVD ``U S Vᵀ``, and the translation: the composed transform is rigid (a proper SE(3) element).
``project=False`` gives the dataset's raw product.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dynslam_cli.errors import DynslamError

T_ROS = np.array([[-1.0, 0.0, 0.0, 0.0],
                  [0.0, 0.0, 1.0, 0.0],
                  [0.0, 1.0, 0.0, 0.0],
                  [0.0, 0.0, 0.0, 1.0]])

T_M_RAW = np.array([[1.0157, 0.1828, -0.2389, 0.0113],
                    [0.0009, -0.8431, -0.6413, -0.0098],
                    [-0.3009, 0.6147, -0.8085, 0.0111],
                    [0.0, 0.0, 0.0, 1.0]])

# The scale of T_m's 3×3 block (the cube root of its determinant): metric depth = PNG value / 5000 × this.
DEPTH_SCALE_FACTOR = float(np.cbrt(np.linalg.det(T_M_RAW[:3, :3])))

# Laser-scanned reference cloud: archive and the folder `dynslam download bonn/reference` makes.
REFERENCE_ARCHIVE = "rgbd_bonn_groundtruth_1mm_section.zip"
REFERENCE_FOLDER = "rgbd_bonn_reference"


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to the 3×3 matrix ``M`` (Frobenius norm), via SVD."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return U @ D @ Vt


def rigid_T_m() -> np.ndarray:
    """``T_m`` with its 3×3 block projected onto SO(3) (translation kept)."""
    T = T_M_RAW.copy()
    T[:3, :3] = project_to_so3(T_M_RAW[:3, :3])
    return T


def gt_to_reference(T_gt: np.ndarray, project: bool = True) -> np.ndarray:
    """Camera pose(s) in the reference cloud's frame from ground-truth pose(s) (4×4 or N×4×4):
    ``T_ros · T_gt · T_ros · T_m`` (``T_m`` made rigid unless ``project`` is False).

    The result is the camera (optical frame) to reference-cloud transform.  A reconstruction
    whose world frame is the camera frame of frame ``k`` goes to the reference frame with
    ``gt_to_reference(T_gt[k])``; an estimated trajectory can be aligned (Umeyama, SE(3)) to
    ``gt_to_reference(gt_poses)`` and the same alignment applied to its mesh.
    """
    T_gt = np.asarray(T_gt, dtype=np.float64)
    T_m = rigid_T_m() if project else T_M_RAW
    return T_ROS @ T_gt @ T_ROS @ T_m


def reference_cloud(root: str | Path) -> Path:
    """The reference point cloud (PLY) under a data root, as `dynslam download bonn/reference`
    leaves it; a clear error when it is absent."""
    folder = Path(root) / REFERENCE_FOLDER
    plys = sorted(folder.rglob("*.ply")) if folder.is_dir() else []
    if not plys:
        raise DynslamError(f"Bonn reference cloud not found in {folder}: run `dynslam download bonn/reference`")
    return plys[0]
