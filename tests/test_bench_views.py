"""The reversed view of benchmarks/bench_views.py (the benchmark itself is run by hand)."""

from pathlib import Path

import numpy as np
from test_data_helpers import data_cfg, make_folder

import benchmark_scripts  # tests/benchmark_scripts.py
from dynslam_cli.data.open import open_sequence

B = benchmark_scripts.load("bench_views")
CFG = {"intrinsics": [30.0, 30.0, 16.0, 12.0]}


class TestReversedView:
    def test_frames_come_in_reverse_order_with_their_ground_truth(self, tmp_path: Path):
        src = make_folder(tmp_path / "seq", n=5)
        fwd = open_sequence(str(src), data_cfg(**CFG))
        rev = open_sequence(str(B.reversed_view(src, tmp_path / "rev")), data_cfg(**CFG))
        assert len(rev) == len(fwd) == 5
        for i in range(5):
            a, b = fwd[4 - i], rev[i]
            assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
            assert np.allclose(a.pose_c2w, b.pose_c2w)

    def test_time_stamps_are_mirrored_and_increase(self, tmp_path: Path):
        src = make_folder(tmp_path / "seq", n=4)  # stamps 0.0 0.1 0.2 0.3
        dst = B.reversed_view(src, tmp_path / "rev")
        for name in B.LISTS:
            _, rows = B._entries(dst / name)
            stamps = [t for t, _ in rows]
            assert stamps == sorted(stamps)
            assert np.allclose(stamps, [0.0, 0.1, 0.2, 0.3][:len(stamps)])
        _, rgb = B._entries(dst / "rgb.txt")
        assert rgb[0][1].startswith("rgb/0.300000")  # the last image first

    def test_the_images_are_linked_not_copied(self, tmp_path: Path):
        src = make_folder(tmp_path / "seq", n=2)
        dst = B.reversed_view(src, tmp_path / "rev")
        assert (dst / "rgb").is_symlink() and (dst / "depth").is_symlink()
        assert B.reversed_view(src, dst) == dst  # again over itself: the same view
