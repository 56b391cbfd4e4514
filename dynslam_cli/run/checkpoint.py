"""What a checkpoint belongs to, and writing / reading it.

A checkpoint records its identity (:func:`run_identity`: the sequence with a hash of its frame list,
the flattened resolved config, the code version) beside the SLAM and motion state and the random
generators; ``--resume`` refuses a checkpoint whose record differs and names the difference
(:func:`identity_mismatch`).  Checkpoints of older versions, which lack the record, are refused (they
cannot be checked): such a run starts again with ``--overwrite``.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import random
import subprocess
from pathlib import Path
from typing import Optional

import numpy as np

from dynslam_cli.errors import DynslamError
from dynslam_cli.utils.io import atomic_path


@functools.lru_cache(maxsize=None)
def code_version() -> str:
    """The package version, plus ``git describe --always --dirty --tags`` of the source checkout when
    the package runs from one (worked out once per process)."""
    from dynslam_cli import __version__ as ver

    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return ver
    try:
        r = subprocess.run(["git", "-C", str(root), "describe", "--always", "--dirty", "--tags"],
                           capture_output=True, text=True, timeout=10,
                           env={**os.environ, "GIT_OPTIONAL_LOCKS": "0"})  # never take the index lock
    except (OSError, subprocess.SubprocessError):
        return ver
    desc = r.stdout.strip()
    return f"{ver}+git.{desc}" if r.returncode == 0 and desc else ver


def sequence_identity(spec: str, seq) -> dict:
    """What a run's sequence is: spec, dataset, name and a hash of the cut frame list (timestamps and
    rgb/depth file names)."""
    h = hashlib.sha256()
    for stamp, rec in zip(seq.stamps, seq.records, strict=True):
        h.update(f"{stamp} {Path(rec.rgb).name} {Path(rec.depth).name}\n".encode())
    return {"spec": str(spec), "dataset": seq.dataset, "name": seq.name, "frames": len(seq),
            "frames_sha256": h.hexdigest()}


def flatten(d: dict, prefix: str = "") -> dict:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def run_identity(spec: str, seq, cfg, device: str = "cpu") -> dict:
    """What a checkpoint belongs to: the sequence, the flattened resolved config, the code version and
    the kind of device it ran on (``run.device: auto`` resolves differently between machines, and a
    random generator's state belongs to its device)."""
    from dynslam_cli.config.loader import config_to_dict

    return {"sequence": sequence_identity(spec, seq), "config": flatten(config_to_dict(cfg)),
            "code": code_version(), "device": device}


# Keys that say when a run stops or saves and where files live, not what it computes: free on --resume.
RESUME_FREE_KEYS = ("run.checkpoint_every", "run.keep_checkpoint", "run.results_root", "data.root")
_ABSENT = "<absent>"


def _show(v) -> str:
    try:
        return json.dumps(v)
    except (TypeError, ValueError):
        return str(v)


def differing_keys(old: dict, new: dict) -> list[str]:
    """The keys of two flattened configs (:func:`flatten`) whose values differ, a key one lacks included, other than
    :data:`RESUME_FREE_KEYS` (sorted)."""
    return [k for k in sorted(set(old) | set(new))
            if k not in RESUME_FREE_KEYS and old.get(k, _ABSENT) != new.get(k, _ABSENT)]


def identity_mismatch(old: dict, new: dict) -> Optional[str]:
    """The first difference between two :func:`run_identity` records (sequence, config, code), or None."""
    so, sn = old.get("sequence") or {}, new["sequence"]
    name_old, name_new = f"{so.get('dataset')}/{so.get('name')}", f"{sn['dataset']}/{sn['name']}"
    if name_old != name_new:
        return f"sequence {sn['spec']} differs (old {name_old}, new {name_new})"
    if so.get("frames_sha256") != sn["frames_sha256"]:
        return (f"sequence {sn['spec']} differs (old {so.get('frames')} frames with list hash "
                f"{str(so.get('frames_sha256'))[:12]}, new {sn['frames']} frames with {sn['frames_sha256'][:12]})")
    co, cn = old.get("config") or {}, new["config"]
    diff = differing_keys(co, cn)
    if diff:
        k = diff[0]
        more = f" and {len(diff) - 1} more ({', '.join(diff[1:4])})" if len(diff) > 1 else ""
        return f"config key {k} differs (old {_show(co.get(k, _ABSENT))}, new {_show(cn.get(k, _ABSENT))}){more}"
    if old.get("code") != new["code"]:
        return f"code version differs (old {old.get('code')}, new {new['code']})"
    was, now = old.get("device", "cpu"), new.get("device", "cpu")  # checkpoints before the field: the CPU
    if was != now:
        return f"device differs (the checkpoint ran on {was}, this run would use {now}: pass --device {was})"
    return None


def save(path: Path, slam, next_frame: int, timings: dict, identity: dict, loop) -> None:
    import torch

    state = {"identity": identity, "slam": slam.state_dict(), "next_frame": next_frame, "timings": timings,
             "torch_rng": torch.get_rng_state(), "np_rng": np.random.get_state(), "py_rng": random.getstate(),
             "loop": loop.state_dict()}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load(path: Path) -> dict:
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:
        raise DynslamError(f"cannot read checkpoint {path}: {exc}") from None
    if not isinstance(state, dict):
        raise DynslamError(f"cannot read checkpoint {path}: not a dynslam checkpoint")
    return state


def resume_state(path: Path, identity: dict) -> dict:
    """The checkpoint at ``path`` when it belongs to ``identity``; else a DynslamError naming the difference."""
    state = load(path)
    old = state.get("identity")
    if not isinstance(old, dict):
        raise DynslamError(f"--resume: {path} was written by an older dynslam and does not record its sequence, "
                           f"config and code version, so it cannot be checked; start again with --overwrite")
    why = identity_mismatch(old, identity)
    if why:
        raise DynslamError(f"--resume: {why} from the checkpoint in {path.parent}; resume with the same sequence "
                           f"and options, or start again with --overwrite")
    return state
