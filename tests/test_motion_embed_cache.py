import numpy as np
import torch

from dynslam_cli.motion.embed_cache import MAX_AGE, EmbeddingCache, overlap_iou


class CountingEncoder:
    """Embedding = (mean colour of the instance's pixels, pixel count); counts the instances encoded."""

    name = "counting"
    dim = 4

    def __init__(self):
        self.encoded = 0

    def encode(self, rgb, ids):
        k = int(ids.max(initial=0))
        self.encoded += k
        out = np.zeros((k, 4), np.float32)
        for i in range(k):
            m = ids == i + 1
            out[i, :3] = rgb[m].mean(0) if m.any() else 0
            out[i, 3] = m.sum()
        return out


def two_boxes(shift=0):
    ids = np.zeros((64, 64), np.int32)
    ids[8:40, 4 + shift:28 + shift] = 1
    ids[40:60, 36:60] = 2
    return ids


def rgb_image(seed=0):
    return np.random.default_rng(seed).integers(0, 255, (64, 64, 3), dtype=np.uint8)


class TestOverlapIou:
    def test_known_values(self):
        a = np.array([[1, 1, 0, 0], [1, 1, 2, 2]])
        b = np.array([[1, 1, 1, 0], [0, 0, 2, 2]])
        iou = overlap_iou(a, 2, b, 2)
        assert iou.shape == (2, 2)
        np.testing.assert_allclose(iou, [[2 / 5, 0.0], [0.0, 1.0]])

    def test_empty(self):
        assert overlap_iou(np.zeros((4, 4), int), 0, np.ones((4, 4), int), 1).shape == (0, 1)
        assert overlap_iou(np.ones((4, 4), int), 1, np.zeros((4, 4), int), 0).shape == (1, 0)


class TestEmbeddingCache:
    def test_first_frame_encodes_everything_like_the_encoder(self):
        enc, cache = CountingEncoder(), EmbeddingCache()
        rgb, ids = rgb_image(), two_boxes()
        emb, n = cache.encode(enc, rgb, ids, 2)
        assert n == 2 and enc.encoded == 2
        np.testing.assert_array_equal(emb, CountingEncoder().encode(rgb, ids))

    def test_unchanged_instances_are_reused_until_max_age(self):
        enc, cache = CountingEncoder(), EmbeddingCache()
        rgb, ids = rgb_image(), two_boxes()
        first, _ = cache.encode(enc, rgb, ids, 2)
        counts = [cache.encode(enc, rgb_image(1), ids, 2)[1] for _ in range(MAX_AGE + 1)]
        assert counts == [0] * MAX_AGE + [2]  # carried MAX_AGE frames, then computed again

    def test_a_moved_instance_is_encoded_again(self):
        enc, cache = CountingEncoder(), EmbeddingCache()
        rgb = rgb_image()
        first, _ = cache.encode(enc, rgb, two_boxes(), 2)
        emb, n = cache.encode(enc, rgb, two_boxes(shift=12), 2)  # box 1 moved by half its width
        assert n == 1
        np.testing.assert_array_equal(emb[1], first[1])
        np.testing.assert_array_equal(emb[0], CountingEncoder().encode(rgb, two_boxes(shift=12))[0])

    def test_ids_are_matched_by_overlap_not_by_number(self):
        enc, cache = CountingEncoder(), EmbeddingCache()
        rgb, ids = rgb_image(), two_boxes()
        first, _ = cache.encode(enc, rgb, ids, 2)
        swapped = np.where(ids == 1, 2, np.where(ids == 2, 1, 0)).astype(np.int32)
        emb, n = cache.encode(enc, rgb, swapped, 2)
        assert n == 0
        np.testing.assert_array_equal(emb, first[::-1])

    def test_no_instances_and_a_new_size(self):
        enc, cache = CountingEncoder(), EmbeddingCache()
        emb, n = cache.encode(enc, rgb_image(), np.zeros((64, 64), np.int32), 0)
        assert emb.shape == (0, 4) and n == 0
        big = np.zeros((128, 128), np.int32)
        big[:50, :50] = 1
        _, n = cache.encode(enc, np.zeros((128, 128, 3), np.uint8), big, 1)
        assert n == 1

    def test_state_round_trip(self):
        enc, cache = CountingEncoder(), EmbeddingCache()
        rgb, ids = rgb_image(), two_boxes()
        cache.encode(enc, rgb, ids, 2)
        d = cache.state_dict()
        assert all(isinstance(v, torch.Tensor) for v in d.values())
        other = EmbeddingCache()
        other.load_state_dict(d)
        a = cache.encode(CountingEncoder(), rgb, ids, 2)
        b = other.encode(CountingEncoder(), rgb, ids, 2)
        np.testing.assert_array_equal(a[0], b[0])
        assert a[1] == b[1] == 0
        other.load_state_dict({})
        assert other.ids is None
