"""The simulation of benchmarks/bench_ba_bias.py (the benchmark itself is run by hand)."""

import pytest

import benchmark_scripts  # tests/benchmark_scripts.py

B = benchmark_scripts.load("bench_ba_bias")


class TestSimulate:
    def test_noise_free_bundle_adjustment_keeps_the_length(self):
        # (nearly) exact observations: the estimated translation is the true one
        assert B.simulate(0, 1e-6, 1e-3, "depth", 4, 0.05) == pytest.approx(1.0, abs=1e-3)

    @pytest.mark.parametrize("on", ["depth", "disparity"])
    def test_noisy_ratio_is_near_one_and_repeats(self, on):
        r = B.simulate(3, 0.002, 0.5, on, 4, 0.05)
        assert abs(r - 1.0) < 0.05
        assert B.simulate(3, 0.002, 0.5, on, 4, 0.05) == r  # seeded

    def test_seeds_differ(self):
        assert B.simulate(1, 0.01, 0.5, "depth", 4, 0.05) != B.simulate(2, 0.01, 0.5, "depth", 4, 0.05)
