import numpy as np

from dynslam_cli.slam.keyframes import depth_edges


def test_depth_edges_mark_both_sides_of_a_step_and_holes():
    d = np.full((10, 12), 2.0, np.float32)
    d[:, 6:] = 1.0
    d[8, 1] = 0.0
    e = depth_edges(d, 0.05, 0)
    assert e[:, 5].all() and e[:, 6].all() and not e[:, 3].any() and not e[:, 9].any()
    assert e[7, 1] and e[8, 0] and not e[8, 1]  # the hole's valid neighbours, not the hole itself
    assert depth_edges(d, 0.05, 2)[:, 3:9].all()
    assert not depth_edges(np.full((5, 5), 2.0, np.float32), 0.05, 2).any()
