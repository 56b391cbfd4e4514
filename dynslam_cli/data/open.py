"""`open_sequence(spec, cfg)`: from a name or a folder to a :class:`Sequence`.

Specs: ``tum/fr3_walking_xyz`` (→ ``<root>/rgbd_dataset_freiburg3_walking_xyz`` or
``<root>/tum/rgbd_dataset_…``), ``bonn/crowd`` (→ ``<root>/rgbd_bonn_crowd`` or
``<root>/bonn/rgbd_bonn_crowd``), ``synth/PRESET`` (rendered on first use into
``<root>/synth/<PRESET>_<W>x<H>_<N>f_s<seed>``) or a folder path.  The root is ``data.root``,
else ``$DYNSLAM_DATA``, else ``data/``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from dynslam_cli.data.names import (
    SequenceId,
    folder_name,
    identify,
    is_known,
    known_names,
)
from dynslam_cli.data.sequence import Sequence
from dynslam_cli.errors import DynslamError


def data_root(cfg=None) -> Path:
    """``cfg.data.root``, else ``$DYNSLAM_DATA``, else ``data/`` (relative to the working folder)."""
    root = getattr(getattr(cfg, "data", None), "root", "") if cfg is not None else ""
    if root:
        return Path(root).expanduser()
    env = os.environ.get("DYNSLAM_DATA", "")
    return Path(env).expanduser() if env else Path("data")


# The sensor settings a synthetic scene's folder name carries, each only where it differs from the renderer's default
# (the defaults' scenes keep their plain names): a scene rendered with other noise is another folder, not the cache.
SENSOR_TAGS = (("depth_noise", "dn"), ("depth_holes", "dh"), ("rgb_noise", "cn"))


def synth_cache_dir(preset: str, cfg, root: Path | None = None) -> Path:
    """The folder ``synth/PRESET`` is rendered into and read from with ``cfg.synth``'s settings:
    ``PRESET_WxH_Nf_sSEED``, then ``_dnX``, ``_dhX``, ``_cnX`` for sensor settings off their defaults.  A
    scene already there whose ``synth.json`` says it was rendered with other sensor settings (a folder
    from an older version, renamed or edited by hand) is refused."""
    from dynslam_cli.data.tum import read_synth_json
    from dynslam_cli.synth.config import SynthConfig

    s = cfg.synth
    root = data_root(cfg) if root is None else Path(root)
    default = SynthConfig()
    tags = "".join(f"_{tag}{getattr(s, key):g}" for key, tag in SENSOR_TAGS if getattr(s, key) != getattr(default, key))
    out = root / "synth" / f"{preset}_{s.width}x{s.height}_{s.frames}f_s{s.seed}{tags}"
    if (out / "rgb.txt").is_file() and (out / "synth.json").is_file():
        sensor = read_synth_json(out / "synth.json").get("sensor") or {}
        for key, _ in SENSOR_TAGS:
            want, got = float(getattr(s, key)), sensor.get(key)
            if isinstance(got, (int, float)) and float(got) != want:  # not a number: read_folder says so
                raise DynslamError(f"{out} holds synth/{preset} rendered with {key} {float(got):g}, not synth.{key} "
                                   f"{want:g}; delete the folder to render it again, or give the setting it was "
                                   "made with")
    return out


def render_synth(preset: str, cfg, out_dir: Path, progress: bool = True) -> Path:
    """Render ``preset`` into ``out_dir`` atomically (a temporary folder beside it, then renamed)."""
    try:
        from dynslam_cli.synth.render import render_preset
    except ImportError as exc:
        raise DynslamError(f"cannot render synth/{preset}: the synthetic renderer is not available ({exc})") from None
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        render_preset(preset, tmp, cfg.synth, frames=cfg.synth.frames, progress=progress)
        if not (tmp / "rgb.txt").is_file():
            raise DynslamError(f"rendering synth/{preset} into {tmp} produced no rgb.txt")
        try:
            os.replace(tmp, out_dir)
        except OSError:
            if not (out_dir / "rgb.txt").is_file():  # not a concurrent render finishing first
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def _named_folder(sid: SequenceId, root: Path) -> Path:
    folder = folder_name(sid.dataset, sid.name)
    if folder is None:
        known = ", ".join(known_names(sid.dataset))
        raise DynslamError(f"unknown sequence '{sid.key}'; known {sid.dataset} sequences: {known} "
                           f"(or give a folder path)")
    candidates = [root / folder, root / sid.dataset / folder]
    for cand in candidates:
        if cand.is_dir():
            return cand
    if not is_known(sid.dataset, sid.name):
        known = ", ".join(known_names(sid.dataset))
        raise DynslamError(f"unknown sequence '{sid.key}' (no folder {candidates[0]}); known "
                           f"{sid.dataset} sequences: {known} (or give a folder path)")
    raise DynslamError(f"sequence '{sid.key}' not found: looked for {candidates[0]} and {candidates[1]}; "
                       f"run `dynslam download {sid.key} --data-root {root}` (or set --data-root / $DYNSLAM_DATA)")


def resolve_path(spec: str, cfg, progress: bool = True) -> tuple[SequenceId, Path]:
    """The identified sequence and its folder (rendering a synthetic preset when needed)."""
    sid = identify(spec)
    if sid.path is not None:
        if not sid.path.is_dir():
            raise DynslamError(f"sequence folder {sid.path} does not exist (and '{spec}' is not a "
                               f"name like tum/fr3_walking_xyz, bonn/crowd or synth/PRESET)")
        return sid, sid.path
    root = data_root(cfg)
    if sid.dataset == "synth":
        out = synth_cache_dir(sid.name, cfg, root)
        if not (out / "rgb.txt").is_file():
            render_synth(sid.name, cfg, out, progress=progress)
        return sid, out
    return sid, _named_folder(sid, root)


def open_sequence(spec: str, cfg=None, progress: bool = True) -> Sequence:
    """Open the sequence ``spec`` with the data settings of ``cfg`` (resolved for that sequence
    from configs/ when None)."""
    if cfg is None:
        from dynslam_cli.config import load_config

        sid0 = identify(spec)
        cfg = load_config(sid0.dataset, sid0.name)
    from dynslam_cli.data.tum import read_folder

    sid, folder = resolve_path(spec, cfg, progress=progress)
    return read_folder(folder, cfg, dataset=sid.dataset, name=sid.name, spec=str(spec))
