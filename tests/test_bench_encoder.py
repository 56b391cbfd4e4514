"""The embedding agreement of benchmarks/bench_encoder.py (the benchmark itself is run by hand)."""

import numpy as np
import pytest

import benchmark_scripts  # tests/benchmark_scripts.py

B = benchmark_scripts.load("bench_encoder")


class TestAgreement:
    def test_identical_embeddings_agree_fully(self):
        x = np.random.default_rng(0).standard_normal((6, 8))
        a = B.agreement(x, 3.0 * x)  # the scale of an embedding does not matter
        assert a["cos_min"] == pytest.approx(1.0)
        assert a["cos_median"] == pytest.approx(1.0)
        assert a["nn_same"] == 1.0

    def test_known_values(self):
        ref = np.array([[1.0, 0.0], [0.9, 0.1], [0.0, 1.0]])
        # crop 2 turned by 90 degrees onto crop 0: cosine 0 with itself; nearest crops before 1, 0, 1 and
        # after 2, 0 (ties: the first), 0: only crop 1 keeps its nearest
        emb = np.array([[1.0, 0.0], [0.9, 0.1], [1.0, 0.0]])
        a = B.agreement(ref, emb)
        assert a["cos_min"] == pytest.approx(0.0)
        assert a["cos_median"] == pytest.approx(1.0)
        assert a["nn_same"] == pytest.approx(1 / 3)

    def test_shapes_must_match(self):
        with pytest.raises(ValueError):
            B.agreement(np.ones((3, 4)), np.ones((2, 4)))
