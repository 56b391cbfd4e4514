"""The oracle labelling of benchmarks/bench_segment.py (the benchmark itself is run by hand)."""

import numpy as np

import benchmark_scripts  # tests/benchmark_scripts.py

B = benchmark_scripts.load("bench_segment")


class TestOracleMask:
    def test_majority_per_segment(self):
        ids = np.array([[1, 1, 2, 2],
                        [1, 1, 2, 2],
                        [0, 0, 3, 3]])
        gt = np.array([[1, 1, 1, 0],
                       [1, 0, 0, 0],
                       [1, 1, 1, 0]], bool)
        # segment 1: 3 of 4 dynamic -> dynamic; 2: 1 of 4 -> static; 3: 1 of 2 (not more than half) -> static;
        # 0 (no segment) is never dynamic
        expected = np.array([[1, 1, 0, 0],
                             [1, 1, 0, 0],
                             [0, 0, 0, 0]], bool)
        np.testing.assert_array_equal(B.oracle_mask(ids, gt), expected)

    def test_extent_is_masked_by_the_ids_majority(self):
        ids = np.array([[1, 1, 0, 2]])
        extent = np.array([[1, 1, 1, 2]])  # the unlabelled pixel belongs to segment 1's extent
        gt = np.array([[1, 1, 1, 0]], bool)
        np.testing.assert_array_equal(B.oracle_mask(ids, gt, extent), [[1, 1, 1, 0]])
        np.testing.assert_array_equal(B.oracle_mask(ids, gt), [[1, 1, 0, 0]])

    def test_no_mover_no_mask(self):
        ids = np.arange(12).reshape(3, 4)
        assert not B.oracle_mask(ids, np.zeros((3, 4), bool)).any()
