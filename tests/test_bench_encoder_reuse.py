"""The cache replay of benchmarks/bench_encoder_reuse.py (the benchmark itself is run by hand)."""

import numpy as np

import benchmark_scripts  # tests/benchmark_scripts.py

B = benchmark_scripts.load("bench_encoder_reuse")


def _frame(thumbs, embs):
    return np.array(thumbs, np.float32), np.array(embs, np.float32)


class TestReplay:
    def test_a_close_thumbnail_takes_the_cached_embedding(self):
        frames = [_frame([[0, 0], [100, 100]], [[1, 0], [0, 1]]),
                  _frame([[0.5, 0.5], [50, 50]], [[0.8, 0.6], [0.6, 0.8]])]
        reused, given = B.replay(frames, tau=1.0, age=5)
        assert reused.tolist() == [False, False, True, False]
        assert np.allclose(given, [[1, 0], [0, 1], [1, 0], [0.6, 0.8]])

    def test_crops_of_one_frame_do_not_reuse_each_other(self):
        reused, _ = B.replay([_frame([[0, 0], [0, 0]], [[1, 0], [0, 1]])], tau=1.0, age=5)
        assert reused.tolist() == [False, False]

    def test_cache_entries_expire_after_age_frames(self):
        frames = [_frame([[0, 0]], [[1, 0]]), _frame([[9, 9]], [[0, 1]]), _frame([[0, 0]], [[1, 0]])]
        assert B.replay(frames, tau=1.0, age=2)[0].tolist() == [False, False, True]
        assert B.replay(frames, tau=1.0, age=1)[0].tolist() == [False, False, False]

    def test_empty_frames(self):
        reused, given = B.replay([_frame(np.zeros((0, 2)), np.zeros((0, 2)))], tau=1.0, age=5)
        assert reused.shape == (0,) and given.shape == (0, 2)


class TestThumbnails:
    def test_area_average_of_a_flat_crop(self):
        crops = np.full((2, 160, 160, 3), 7, np.uint8)
        t = B.thumbnails(crops)
        assert t.shape == (2, B.THUMB * B.THUMB * 3) and np.all(t == 7)
