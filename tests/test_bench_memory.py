"""benchmarks/bench_memory.py: its rows on a tiny run (the benchmark itself is run by hand)."""

import benchmark_scripts  # tests/benchmark_scripts.py
from tiny_runs import tiny_sets, walker_fixture

B = benchmark_scripts.load("bench_memory")
walker = walker_fixture(96, 72, 6)


def test_a_row_every_few_frames_and_the_last(walker, tmp_path):
    sets = [s for s in tiny_sets() if s != "--set"]
    res = B.measure(str(walker), 6, 4, tmp_path / "run", sets, progress=False)
    assert res["frames"] == 6 and [r["frames"] for r in res["rows"]] == [4, 6]
    row = res["rows"][-1]
    assert row["frames_tracked"] == 6 and row["map_keyframes"] >= 1 and row["rss_mb"] > 0
    assert res["peak_rss_mb"] >= max(r["peak_mb"] for r in res["rows"]) > 0
    assert (tmp_path / "run" / "run.json").is_file()
