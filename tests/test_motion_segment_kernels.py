"""The geometric segmenter's numba kernels against the numpy expressions they replace (bit for bit),
and known values."""

from __future__ import annotations

import numpy as np

from dynslam_cli.motion import _segment_kernels as kernels


def _numpy_normals(P):
    du = np.zeros_like(P)
    dv = np.zeros_like(P)
    du[:, 1:-1] = P[:, 2:] - P[:, :-2]
    dv[1:-1] = P[2:] - P[:-2]
    n = np.cross(du, dv)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def _numpy_step_edges(dm, lab, depth_jump, color_jump):
    valid = dm > 0
    edge = ~valid
    for axis in (0, 1):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(0, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        dmin = np.minimum(dm[a], dm[b])
        step = np.abs(dm[a] - dm[b])
        e = step > depth_jump * dmin
        if lab is not None:
            dc = np.linalg.norm(lab[a] - lab[b], axis=-1)
            e |= (dc > color_jump) & (step > 0.25 * depth_jump * dmin)
        e &= valid[a] & valid[b]
        edge[a] |= e
        edge[b] |= e
    return edge


def _numpy_creases(n, smooth, o, cos_max, edge):
    edge = edge.copy()
    for axis in (0, 1):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(0, -o), slice(o, None)
        a, b = tuple(a), tuple(b)
        e = smooth[a] & smooth[b] & ((n[a] * n[b]).sum(-1) < cos_max)
        edge[a] |= e
        edge[b] |= e
    return edge


def _depth(rng, h=37, w=53):
    """Piecewise-smooth depth with steps, a slanted plane and holes."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    d = 2.0 + 0.01 * x + 0.3 * (x > w / 2) + 0.2 * (y > h / 3) * (x < w / 4) + rng.normal(0, 0.02, (h, w))
    d[rng.random((h, w)) < 0.05] = 0
    return d.astype(np.float32)


class TestPoints:
    def test_matches_numpy(self):
        rng = np.random.default_rng(3)
        dm = _depth(rng)
        u = rng.normal(0, 0.5, dm.shape[1]).astype(np.float32)
        v = rng.normal(0, 0.5, dm.shape[0]).astype(np.float32)
        np.testing.assert_array_equal(kernels.points(dm, u, v),
                                      np.stack([dm * u[None, :], dm * v[:, None], dm], -1))


class TestNormals:
    def test_matches_numpy_bit_for_bit(self):
        rng = np.random.default_rng(0)
        P = rng.normal(0, 1, (23, 31, 3)).astype(np.float32)
        P[5, 7] = P[5, 9]  # a zero difference: the tiny-norm branch
        wsum = rng.uniform(0, 2, P.shape[:2]).astype(np.float32)
        wsum[3, 4] = 0  # no valid pixel in the box: divided by 1e-6
        n = kernels.normals(P, wsum)
        assert n.dtype == np.float32 and n.shape == P.shape
        np.testing.assert_array_equal(n, _numpy_normals(P / np.maximum(wsum, 1e-6)[..., None]))

    def test_plane_facing_the_camera(self):
        y, x = np.mgrid[0:9, 0:11].astype(np.float32)
        P = np.stack([x, y, np.full_like(x, 3.0)], -1)  # z = 3: normal along +z (x right, y down)
        n = kernels.normals(P, np.ones(P.shape[:2], np.float32))
        np.testing.assert_allclose(n[1:-1, 1:-1], np.broadcast_to([0, 0, 1], (7, 9, 3)), atol=1e-7)
        assert not n[0].any() and not n[:, -1].any()  # borders: no difference, no normal


class TestStepEdges:
    def test_matches_numpy_with_and_without_colour(self):
        rng = np.random.default_rng(1)
        dm = _depth(rng)
        lab = rng.normal(50, 30, dm.shape + (3,)).astype(np.float32)
        for jump in (0.04, 0.01):
            np.testing.assert_array_equal(kernels.step_edges(dm, lab, jump, 40.0, 0.25 * jump),
                                          _numpy_step_edges(dm, lab, jump, 40.0))
            np.testing.assert_array_equal(kernels.step_edges(dm, np.zeros((0, 0, 3), np.float32), jump, 40.0,
                                                             0.25 * jump),
                                          _numpy_step_edges(dm, None, jump, 40.0))

    def test_a_step_marks_both_sides(self):
        dm = np.full((4, 6), 2.0, np.float32)
        dm[:, 3:] = 2.5
        edge = kernels.step_edges(dm, np.zeros((0, 0, 3), np.float32), 0.04, 40.0, 0.01)
        assert edge[:, 2:4].all() and not edge[:, [0, 1, 4, 5]].any()
        dm[1, 1] = 0  # a hole is an edge, and no step is measured against it
        edge = kernels.step_edges(dm, np.zeros((0, 0, 3), np.float32), 0.04, 40.0, 0.01)
        assert edge[1, 1] and not edge[0, 1] and not edge[1, 0]


class TestCreaseEdges:
    def test_matches_numpy(self):
        rng = np.random.default_rng(2)
        n = _numpy_normals(rng.normal(0, 1, (29, 41, 3)).astype(np.float32))
        smooth = rng.random((29, 41)) < 0.8
        edge = rng.random((29, 41)) < 0.1
        for o in (1, 3):
            out = edge.copy()
            kernels.crease_edges(n, smooth, o, np.cos(np.deg2rad(30.0)), out)
            np.testing.assert_array_equal(out, _numpy_creases(n, smooth, o, np.cos(np.deg2rad(30.0)), edge))

    def test_a_right_angle_is_a_crease(self):
        n = np.zeros((3, 8, 3), np.float32)
        n[:, :4] = [0, 0, 1]
        n[:, 4:] = [1, 0, 0]
        edge = np.zeros((3, 8), bool)
        kernels.crease_edges(n, np.ones((3, 8), bool), 1, np.cos(np.deg2rad(30.0)), edge)
        assert edge[:, 3:5].all() and edge.sum() == 6


class TestGrowContinuous:
    def test_band_beside_a_step_joins_the_side_at_its_depth(self):
        dm = np.full((5, 12), 2.0, np.float32)
        dm[:, 6:] = 3.0  # a 1 m step between columns 5 and 6
        labels = np.zeros((5, 12), np.int32)
        labels[:, :3] = 1
        labels[:, 9:] = 2  # columns 3-8: the unlabelled band around the step
        out = kernels.grow_continuous(labels, dm, 0.04)
        assert (out[:, :6] == 1).all() and (out[:, 6:] == 2).all()

    def test_shapes_dtype_and_input_untouched(self):
        rng = np.random.default_rng(3)
        dm = _depth(rng)
        labels = (rng.random(dm.shape) < 0.02).astype(np.int32) * rng.integers(1, 5, dm.shape).astype(np.int32)
        before = labels.copy()
        out = kernels.grow_continuous(labels, dm, 0.04)
        assert out.shape == dm.shape and out.dtype == np.int32
        np.testing.assert_array_equal(labels, before)
        # labelled pixels keep their label; pixels without depth are never grown into
        np.testing.assert_array_equal(out[labels > 0], labels[labels > 0])
        assert (out[(dm <= 0) & (labels == 0)] == 0).all()

    def test_nearest_seed_along_the_surface(self):
        dm = np.full((1, 9), 2.0, np.float32)
        labels = np.zeros((1, 9), np.int32)
        labels[0, 0], labels[0, 8] = 1, 2
        out = kernels.grow_continuous(labels, dm, 0.04)
        assert list(out[0]) == [1, 1, 1, 1, 1, 2, 2, 2, 2]  # the tie at column 4 goes to the seed scanned first

    def test_no_growth_across_steps_or_holes(self):
        dm = np.full((3, 9), 2.0, np.float32)
        dm[:, 4] = 0  # a column without depth
        dm[:, 7:] = 2.5  # and a step of 25 %
        labels = np.zeros((3, 9), np.int32)
        labels[1, 0] = 1
        out = kernels.grow_continuous(labels, dm, 0.04)
        assert (out[:, :4] == 1).all() and (out[:, 4:] == 0).all()
        # a slope of 1 % a pixel is continuous under a 4 % jump, whatever its length
        dm = (2.0 * 1.01 ** np.arange(40, dtype=np.float32))[None].astype(np.float32)
        labels = np.zeros((1, 40), np.int32)
        labels[0, 0] = 3
        assert (kernels.grow_continuous(labels, dm, 0.04) == 3).all()
