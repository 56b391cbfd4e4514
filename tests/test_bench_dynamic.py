"""The repeated-rounds summary of benchmarks/bench_dynamic.py (the benchmark itself is run by hand)."""

import pytest

import benchmark_scripts  # tests/benchmark_scripts.py

B = benchmark_scripts.load("bench_dynamic")


def _row(mode, fps, frame_ms, ate=1.0):
    return {"case": "c", "mode": mode, "ate_cm": ate, "still_cm": 9.0, "fps": fps, "fps_after_first": fps + 0.1,
            "updates": 3, "iou": "—", "median_ms": {"frame": frame_ms, "map": frame_ms / 2},
            "cpu_ms": 1.5 * frame_ms, "cores": 1.5}


class TestAggregate:
    def test_medians_of_speed_first_round_of_accuracy(self):
        agg = B.aggregate([_row("dynamic", 1.0, 700), _row("dynamic", 1.5, 600, ate=1.2), _row("dynamic", 1.2, 900)])
        assert agg["fps"] == 1.2 and agg["fps_after_first"] == pytest.approx(1.3)
        assert agg["median_ms"] == {"frame": 700, "map": 350}
        assert agg["cpu_ms"] == 1050 and agg["cores"] == 1.5  # medians too
        assert agg["ate_cm"] == 1.0 and agg["ate_range_cm"] == (1.0, 1.2) and agg["rounds"] == 3

    def test_one_round_is_that_round(self):
        r = _row("static", 2.5, 400)
        agg = B.aggregate([r])
        assert agg["fps"] == 2.5 and agg["median_ms"] == r["median_ms"] and agg["ate_range_cm"] == (1.0, 1.0)

    def test_a_component_missing_in_a_round_counts_as_zero(self):
        a, b = _row("dynamic", 1.0, 700), _row("dynamic", 1.0, 700)
        a["median_ms"]["wait"] = 8.0
        assert B.aggregate([a, b, dict(a)])["median_ms"]["wait"] == 8.0
        assert B.aggregate([a, b])["median_ms"]["wait"] == 4.0


class TestRoundRatios:
    def test_time_per_frame_over_static_of_the_same_round(self):
        rounds = [[_row("static", 3.0, 300), _row("dynamic", 1.5, 700)],
                  [_row("static", 2.0, 400), _row("dynamic", 1.6, 600)]]
        assert B.round_ratios(rounds, "dynamic") == pytest.approx([2.0, 1.25])

    def test_rounds_without_static_mode_give_nothing(self):
        assert B.round_ratios([[_row("dynamic", 1.5, 700)]], "dynamic") == []
