"""Sequence names: `tum/fr3_walking_xyz`, `bonn/crowd`, `synth/walker` or a folder path.

This module only maps names to datasets and folder names; it does not read any data.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

# TUM RGB-D sequences used by the paper (fr3 dynamic) plus static ones useful for checks.
TUM_SEQUENCES = {
    "fr3_walking_static": "rgbd_dataset_freiburg3_walking_static",
    "fr3_walking_xyz": "rgbd_dataset_freiburg3_walking_xyz",
    "fr3_walking_halfsphere": "rgbd_dataset_freiburg3_walking_halfsphere",
    "fr3_walking_rpy": "rgbd_dataset_freiburg3_walking_rpy",
    "fr3_sitting_static": "rgbd_dataset_freiburg3_sitting_static",
    "fr3_sitting_xyz": "rgbd_dataset_freiburg3_sitting_xyz",
    "fr3_sitting_halfsphere": "rgbd_dataset_freiburg3_sitting_halfsphere",
    "fr3_sitting_rpy": "rgbd_dataset_freiburg3_sitting_rpy",
    "fr3_office": "rgbd_dataset_freiburg3_long_office_household",
    "fr1_desk": "rgbd_dataset_freiburg1_desk",
    "fr1_desk2": "rgbd_dataset_freiburg1_desk2",
    "fr1_room": "rgbd_dataset_freiburg1_room",
    "fr2_xyz": "rgbd_dataset_freiburg2_xyz",
}

# Bonn RGB-D Dynamic sequences (the paper's nine first).
BONN_SEQUENCES = {
    name: f"rgbd_bonn_{name}"
    for name in (
        "balloon", "balloon2", "kidnapping_box", "kidnapping_box2", "crowd", "crowd2", "crowd3",
        "person_tracking", "person_tracking2", "synchronous", "synchronous2",
        "balloon_tracking", "balloon_tracking2", "moving_nonobstructing_box",
        "moving_nonobstructing_box2", "moving_obstructing_box", "moving_obstructing_box2",
        "placing_nonobstructing_box", "placing_nonobstructing_box2", "placing_nonobstructing_box3",
        "placing_obstructing_box", "removing_nonobstructing_box", "removing_nonobstructing_box2",
        "removing_obstructing_box", "static", "static_close_far",
    )
}

DATASETS = ("tum", "bonn", "synth")


@dataclass(frozen=True)
class SequenceId:
    dataset: str  # "tum", "bonn" or "synth"
    name: str  # short name: fr3_walking_xyz, crowd, walker, or a folder's name
    path: Path | None = None  # the folder when given as a path, else None (resolved under a root)

    @property
    def key(self) -> str:
        return f"{self.dataset}/{self.name}"


def _from_folder_name(folder: str) -> tuple[str, str] | None:
    m = re.fullmatch(r"rgbd_dataset_freiburg(\d)_(.+)", folder)
    if m:
        short = f"fr{m.group(1)}_{m.group(2)}"
        for k, v in TUM_SEQUENCES.items():
            if v == folder:
                short = k
        return "tum", short
    m = re.fullmatch(r"rgbd_bonn_(.+)", folder)
    if m:
        return "bonn", m.group(1)
    return None


def identify(seq: str) -> SequenceId:
    """Tell the dataset and short name of ``seq`` without reading data.

    A string with a known dataset prefix (``tum/``, ``bonn/``, ``synth/``) that is not an existing
    folder is a name; anything else is a folder path whose dataset is guessed from its name
    (``rgbd_dataset_freiburg*``, ``rgbd_bonn_*``, anything containing 'bonn' or 'tum') or from a
    ``synth.json`` marker written by the synthetic renderer.
    """
    text = str(seq).strip()
    prefix, _, rest = text.partition("/")
    if prefix in DATASETS and rest and "/" not in rest and not Path(text).is_dir():
        return SequenceId(prefix, rest)
    path = Path(text)
    folder = path.resolve().name if text not in (".", "") else Path.cwd().name
    if (path / "synth.json").is_file():
        return SequenceId("synth", folder, path)
    guess = _from_folder_name(folder)
    if guess:
        return SequenceId(guess[0], guess[1], path)
    low = folder.lower()
    if "bonn" in low:
        return SequenceId("bonn", folder, path)
    if "tum" in low or "freiburg" in low:
        return SequenceId("tum", folder, path)
    return SequenceId("tum", folder, path)  # the TUM layout is the generic one


def known_names(dataset: str) -> list[str]:
    """The short names of a dataset's table (empty for synth: presets live in the renderer)."""
    table = {"tum": TUM_SEQUENCES, "bonn": BONN_SEQUENCES}.get(dataset, {})
    return sorted(table)


def folder_name(dataset: str, name: str) -> str | None:
    """The dataset's own folder name of a short name (``fr3_walking_xyz`` →
    ``rgbd_dataset_freiburg3_walking_xyz``; ``crowd`` → ``rgbd_bonn_crowd``); names outside the
    tables that follow the dataset's pattern (``fr2_desk``) map by the pattern; else None."""
    if dataset == "tum":
        if name in TUM_SEQUENCES:
            return TUM_SEQUENCES[name]
        m = re.fullmatch(r"fr(\d)_([A-Za-z0-9_]+)", name)
        if m:
            return f"rgbd_dataset_freiburg{m.group(1)}_{m.group(2)}"
        if re.fullmatch(r"rgbd_dataset_freiburg\d_[A-Za-z0-9_]+", name):
            return name
        return None
    if dataset == "bonn":
        if name in BONN_SEQUENCES:
            return BONN_SEQUENCES[name]
        if name.startswith("rgbd_bonn_") and name[len("rgbd_bonn_"):] in BONN_SEQUENCES:
            return name
        return None
    return None


def is_known(dataset: str, name: str) -> bool:
    """Whether ``name`` is in the dataset's table (patterns outside it are 'possible', not known)."""
    folder = folder_name(dataset, name)
    return folder is not None and folder in {"tum": TUM_SEQUENCES, "bonn": BONN_SEQUENCES}.get(dataset, {}).values()
