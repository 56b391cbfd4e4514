"""The motion classifier g(z; θ_C): a 2-layer MLP with a sigmoid, its continual (replay) update
and the optional prior classifier (OR rule)."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator, Optional

import numpy as np
import torch
import torch.nn as nn

from dynslam_cli.errors import DynslamError
from dynslam_cli.utils.adam import Adam


@contextlib.contextmanager
def _few_threads(device: torch.device) -> Iterator[None]:
    """The MLP is tiny: on CPU its ops are latency-bound and intra-op threads only contend (20-40×
    slower on a loaded 2-core machine), so it runs on one thread; the setting is restored after."""
    if device.type != "cpu":
        yield
        return
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


class MLP(nn.Module):
    def __init__(self, in_dim: int, hidden: int = 128, init_bias: float = -2.0):
        super().__init__()
        self.fc1 = nn.Linear(in_dim, hidden)
        self.fc2 = nn.Linear(hidden, 1)
        with torch.no_grad():  # start out calling everything static (p ≈ 0.12)
            self.fc2.weight.mul_(0.1)
            self.fc2.bias.fill_(init_bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # logits
        return self.fc2(torch.relu(self.fc1(x))).squeeze(-1)


class ReplayBuffer:
    """Features of instances seen dynamic; reservoir sampling beyond ``capacity``."""

    def __init__(self, dim: int, capacity: int = 1000, seed: int = 0):
        self.dim, self.capacity = dim, int(capacity)
        self.items = np.zeros((0, dim), np.float32)
        self.seen = 0
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self.items)

    def add(self, feats: np.ndarray) -> None:
        for f in np.asarray(feats, np.float32).reshape(-1, self.dim):
            self.seen += 1
            if len(self.items) < self.capacity:
                self.items = np.concatenate([self.items, f[None]])
            else:
                j = int(self.rng.integers(0, self.seen))
                if j < self.capacity:
                    self.items[j] = f

    def sample(self, n: int) -> np.ndarray:
        if n <= 0 or len(self.items) == 0:
            return np.zeros((0, self.dim), np.float32)
        idx = self.rng.choice(len(self.items), size=min(n, len(self.items)), replace=False)
        return self.items[idx]

    def state_dict(self) -> dict:
        return {"items": torch.from_numpy(self.items.copy()), "seen": self.seen, "rng": self.rng.bit_generator.state}

    def load_state_dict(self, d: dict) -> None:
        items = d["items"]
        items = items.numpy() if isinstance(items, torch.Tensor) else items
        self.items = np.asarray(items, np.float32).reshape(-1, self.dim)
        self.seen = int(d["seen"])
        self.rng.bit_generator.state = d["rng"]


class MotionClassifier:
    """g over instance features (embedding, optionally + scaled 3-D centre)."""

    def __init__(self, in_dim: int, hidden: int = 128, lr: float = 0.005, max_steps: int = 50, min_steps: int = 5,
                 seed: int = 0, device: torch.device | str = "cpu"):
        self.in_dim, self.hidden = int(in_dim), int(hidden)
        self.lr, self.max_steps, self.min_steps = float(lr), int(max_steps), int(min_steps)
        self.device = torch.device(device)
        with torch.random.fork_rng(devices=[]):
            torch.random.default_generator.manual_seed(seed)  # the CPU's only: CUDA's stay as they were
            self.net = MLP(self.in_dim, self.hidden).to(self.device)

    def probs(self, feats: np.ndarray) -> np.ndarray:
        if len(feats) == 0:
            return np.zeros(0, np.float32)
        with torch.no_grad(), _few_threads(self.device):
            x = torch.as_tensor(np.asarray(feats, np.float32), device=self.device)
            return torch.sigmoid(self.net(x)).cpu().numpy().astype(np.float32)

    def predict(self, feats: np.ndarray) -> np.ndarray:
        return self.probs(feats) > 0.5

    def fit_steps(self, feats: np.ndarray, labels: np.ndarray, check: Optional[np.ndarray] = None,
                  max_steps: Optional[int] = None, min_steps: Optional[int] = None,
                  weights: Optional[np.ndarray] = None) -> tuple[float, float, int]:
        """Adam on BCE over (feats, labels) until the rows in ``check`` (default: all) are classified as
        labelled and ``min_steps`` are done, or ``max_steps``. Returns (loss before, loss after, steps)."""
        with _few_threads(self.device):
            return self._fit_steps(feats, labels, check, max_steps, min_steps, weights)

    def _fit_steps(self, feats, labels, check, max_steps, min_steps, weights) -> tuple[float, float, int]:
        max_steps = self.max_steps if max_steps is None else max_steps
        min_steps = self.min_steps if min_steps is None else min_steps
        x = torch.as_tensor(np.asarray(feats, np.float32), device=self.device)
        y = torch.as_tensor(np.asarray(labels, np.float32), device=self.device)
        w = None if weights is None else torch.as_tensor(np.asarray(weights, np.float32), device=self.device)
        chk = torch.ones(len(y), dtype=torch.bool, device=self.device) if check is None else \
            torch.as_tensor(np.asarray(check, bool), device=self.device)
        loss_fn = nn.BCEWithLogitsLoss(weight=w)
        opt = Adam(self.net.parameters(), lr=self.lr)
        with torch.no_grad():
            before = float(loss_fn(self.net(x), y))
        steps = 0
        for steps in range(1, max_steps + 1):
            opt.zero_grad()
            logits = self.net(x)
            loss = loss_fn(logits, y)
            loss.backward()
            opt.step()
            if steps >= min_steps:
                with torch.no_grad():
                    ok = ((self.net(x) > 0) == (y > 0.5))[chk].all()
                if bool(ok):
                    break
        with torch.no_grad():
            after = float(loss_fn(self.net(x), y))
        return before, after, steps

    def state_dict(self) -> dict:
        net = {k: v.detach().cpu().clone() for k, v in self.net.state_dict().items()}  # a snapshot, not views
        return {"in_dim": self.in_dim, "hidden": self.hidden, "net": net}

    def load_state_dict(self, d: dict) -> None:
        if int(d["in_dim"]) != self.in_dim or int(d["hidden"]) != self.hidden:
            raise DynslamError(f"classifier state has in_dim {d['in_dim']}/hidden {d['hidden']}, "
                               f"expected {self.in_dim}/{self.hidden} (different encoder or config?)")
        self.net.load_state_dict(d["net"])


# ---- the prior classifier file (`dynslam prior fit`)

PRIOR_FORMAT = "dynslam-prior-v1"


def save_prior(path: str | Path, clf: MotionClassifier, encoder: str, meta: dict) -> Path:
    from dynslam_cli.utils.io import atomic_path

    with atomic_path(path) as tmp:
        torch.save({"format": PRIOR_FORMAT, "encoder": encoder, **clf.state_dict(), "meta": meta}, str(tmp))
    return Path(path)


def load_prior(path: str | Path, encoder: str, dim: int, device: torch.device | str = "cpu") -> MotionClassifier:
    """Load a prior classifier; it must have been fitted with the same encoder."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise DynslamError(f"prior classifier file not found: {p} (motion.prior); create it with `dynslam prior fit --out {p}`")
    try:
        d = torch.load(str(p), map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001
        raise DynslamError(f"cannot read prior classifier {p}: {exc}") from None
    if not isinstance(d, dict) or d.get("format") != PRIOR_FORMAT:
        raise DynslamError(f"{p} is not a prior classifier file written by `dynslam prior fit`")
    if d["encoder"] != encoder or int(d["in_dim"]) != dim:
        raise DynslamError(f"prior {p} was fitted with encoder {d['encoder']} ({d['in_dim']}-d); "
                           f"motion.encoder is {encoder} ({dim}-d): refit it or change motion.encoder")
    clf = MotionClassifier(dim, int(d["hidden"]), device=device)
    clf.load_state_dict(d)
    clf.meta = d.get("meta", {})  # type: ignore[attr-defined]
    return clf


def update_with_replay(clf: MotionClassifier, buffer: Optional[ReplayBuffer], feats: np.ndarray,
                       labels: np.ndarray, n_c: int = 5) -> tuple[float, float, int, int]:
    """One continual update: BCE on the current instances (``feats``, ``labels``) plus ``n_c``
    instances drawn from ``buffer`` (labelled dynamic; no replay when ``buffer`` is None). Stops once
    the current instances are classified as labelled. Returns (loss before, after, steps, replayed)."""
    dim = clf.in_dim
    rep = buffer.sample(n_c) if buffer is not None else np.zeros((0, dim), np.float32)
    x = np.concatenate([np.asarray(feats, np.float32).reshape(-1, dim), rep])
    y = np.concatenate([np.asarray(labels, np.float32).ravel(), np.ones(len(rep), np.float32)])
    check = np.zeros(len(x), bool)
    check[: len(x) - len(rep)] = True
    before, after, steps = clf.fit_steps(x, y, check)
    return before, after, steps, len(rep)
