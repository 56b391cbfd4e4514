import numpy as np

from dynslam_cli.geometry.camera import backproject, pixel_dirs, pixel_index, project, transform
from dynslam_cli.geometry.lie import inv_np, se3_exp_np


def test_backproject_project_round_trip():
    rng = np.random.default_rng(1)
    fx, fy, cx, cy = 50.0, 52.0, 15.5, 11.0
    depth = rng.uniform(0.5, 4.0, size=(24, 32)).astype(np.float32)
    pts = backproject(depth, fx, fy, cx, cy).reshape(-1, 3)
    T = se3_exp_np([0.1, -0.2, 0.3, 0.05, -0.1, 0.2])
    world = transform(T, pts)
    uv, z = project(transform(inv_np(T), world), fx, fy, cx, cy)
    vv, uu = np.mgrid[0:24, 0:32]
    assert np.allclose(uv[:, 0], uu.ravel(), atol=1e-3) and np.allclose(uv[:, 1], vv.ravel(), atol=1e-3)
    assert np.allclose(z, depth.ravel(), atol=1e-5)


def test_pixel_dirs_have_unit_z():
    d = pixel_dirs(np.array([0, 10]), np.array([5, 7]), 10.0, 10.0, 5.0, 5.0)
    assert np.allclose(d[:, 2], 1) and np.allclose(d[0], [-0.5, 0, 1])


def test_pixel_index_nearest_pixel_clipped_into_the_image():
    uv = np.array([[3.4, 1.6], [-2.0, 0.2], [40.0, 9.9]])
    v, u = pixel_index(uv, 10, 32)
    assert v.tolist() == [2, 0, 9] and u.tolist() == [3, 0, 31] and v.dtype == u.dtype == np.int64
