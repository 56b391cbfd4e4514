"""The motion classifier g: learning, continual updates with/without replay, the prior file."""

from __future__ import annotations

import numpy as np
import pytest

from dynslam_cli.errors import DynslamError
from dynslam_cli.motion.classifier import (MotionClassifier, ReplayBuffer, load_prior, save_prior,
                                           update_with_replay)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_starts_static_and_learns_separable_problem():
    rng = np.random.default_rng(0)
    d = 12
    w = _unit(rng.normal(size=d))
    x = _unit(rng.normal(size=(200, d))).astype(np.float32)
    y = (x @ w > 0).astype(np.float32)
    clf = MotionClassifier(d, hidden=32, lr=0.01, seed=0)
    assert not clf.predict(x).any()  # an untrained g calls everything static
    before, after, steps = clf.fit_steps(x[:150], y[:150], max_steps=400, min_steps=400)
    assert after < before and steps == 400
    assert (clf.predict(x[:150]) == (y[:150] > 0.5)).mean() > 0.97
    assert (clf.predict(x[150:]) == (y[150:] > 0.5)).mean() > 0.9  # held out


def test_fit_steps_stops_once_contradictions_are_fixed():
    clf = MotionClassifier(4, hidden=8, lr=0.05, max_steps=200, min_steps=3, seed=0)
    x = np.eye(4, dtype=np.float32)
    y = np.array([1, 0, 0, 0], np.float32)
    _, _, steps = clf.fit_steps(x, y)
    assert 3 <= steps < 200
    assert clf.predict(x).tolist() == [True, False, False, False]


def test_replay_buffer_reservoir_and_state():
    buf = ReplayBuffer(3, capacity=5, seed=1)
    buf.add(np.arange(30, dtype=np.float32).reshape(10, 3))
    assert len(buf) == 5 and buf.seen == 10
    s = buf.sample(3)
    assert s.shape == (3, 3) and len({tuple(r) for r in s}) == 3
    assert buf.sample(99).shape == (5, 3)
    buf2 = ReplayBuffer(3, capacity=5, seed=7)
    buf2.load_state_dict(buf.state_dict())
    assert np.array_equal(buf2.sample(2), buf.sample(2))


def _continual_sequence(replay: bool, seed: int) -> tuple[float, float, int]:
    """A mover A seen moving for 3 frames, then 30 frames of static things, some of which look a bit
    like A. Returns (p(A) after the moving frames, p(A) at the end, number of updates)."""
    rng = np.random.default_rng(seed)
    d = 16
    A = _unit(rng.normal(size=d))
    statics = [_unit(rng.normal(size=d)) for _ in range(3)]
    clf = MotionClassifier(d, hidden=32, lr=0.01, max_steps=50, min_steps=5, seed=0)
    buf = ReplayBuffer(d, 100, seed=0)
    updates = 0

    def noisy(v, s=0.05):
        return _unit(v + s * rng.normal(size=d))

    def frame(feats, labels):
        nonlocal updates
        if (clf.predict(feats) != (labels > 0.5)).any():  # contradiction → update
            update_with_replay(clf, buf if replay else None, feats, labels, 5)
            updates += 1
        buf.add(feats[labels > 0.5])  # instances seen dynamic

    for _ in range(3):
        frame(np.stack([noisy(A)] + [noisy(s) for s in statics]), np.array([1, 0, 0, 0], np.float32))
    p0 = float(clf.probs(A[None])[0])
    for _ in range(30):
        feats = np.stack([noisy(A, 0.5) for _ in range(3)] + [noisy(s) for s in statics])
        frame(feats, np.zeros(len(feats), np.float32))
    return p0, float(clf.probs(A[None])[0]), updates


@pytest.mark.parametrize("seed", [2, 3, 4])
def test_replay_keeps_an_earlier_mover_dynamic(seed):
    p0_r, p_end_r, n_r = _continual_sequence(True, seed)
    p0_n, p_end_n, n_n = _continual_sequence(False, seed)
    assert p0_r > 0.5 and p0_n > 0.5  # learned as dynamic either way
    assert p_end_r > 0.5  # with replay it stays dynamic
    assert p_end_n < 0.5  # without replay it is forgotten
    assert n_r > n_n  # replay costs more updates: the look-alikes keep contradicting


def test_prior_file_round_trip(tmp_path):
    clf = MotionClassifier(6, hidden=8, seed=3)
    x = np.eye(6, dtype=np.float32)
    clf.fit_steps(x, np.array([1, 1, 0, 0, 0, 0], np.float32), max_steps=100, min_steps=100)
    path = save_prior(tmp_path / "p.pt", clf, "color-hist", {"accuracy": 1.0})
    p = load_prior(path, "color-hist", 6)
    assert np.allclose(p.probs(x), clf.probs(x))
    assert p.meta["accuracy"] == 1.0
    with pytest.raises(DynslamError, match="fitted with encoder color-hist"):
        load_prior(path, "effnet-lite0", 1280)
    with pytest.raises(DynslamError, match="prior classifier file not found.*prior fit"):
        load_prior(tmp_path / "none.pt", "color-hist", 6)
    (tmp_path / "junk.pt").write_bytes(b"junk")
    with pytest.raises(DynslamError, match="cannot read prior"):
        load_prior(tmp_path / "junk.pt", "color-hist", 6)
