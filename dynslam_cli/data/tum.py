"""Reader of the TUM RGB-D folder layout (also used by Bonn RGB-D Dynamic and synthetic scenes).

A folder holds ``rgb.txt`` and ``depth.txt`` (``timestamp filename`` per line, ``#`` comments),
optionally ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, camera-to-world) and
optionally ``associations.txt`` (``t_rgb rgb/… t_depth depth/…``), which, when present, is used
as it is instead of associating the two lists.

Association of rgb and depth follows TUM's ``associate.py``: all pairs closer than
``max_time_diff`` (strictly) are candidates, taken smallest difference first, each timestamp used
at most once; the result is ordered by rgb time.  Every list must be sorted by time without
repeats, and the associated depth times must increase with the rgb times (else a DynslamError
names the file and line).

Ground truth per frame, at the rgb timestamp: the pose is **interpolated** (translation linearly,
rotation by slerp) between the two ground-truth samples around the rgb timestamp when the
nearer of them is within ``max_time_diff`` and the two are at most ``2 · max_time_diff`` apart;
otherwise the nearest sample within ``max_time_diff`` is used; otherwise the frame's pose is None.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynslam_cli.data.sequence import FrameRecord, Sequence
from dynslam_cli.data.types import Intrinsics
from dynslam_cli.errors import DynslamError


# --------------------------------------------------------------------------------------------
# text files
@dataclass
class ListEntry:
    timestamp: float
    stamp: str  # the timestamp as written in the file
    file: str  # path relative to the folder
    line: int


def _data_lines(path: Path):
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise DynslamError(f"{path} not found") from None
    except OSError as exc:
        raise DynslamError(f"cannot read {path}: {exc.strerror or exc}") from None
    for no, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if line and not line.startswith("#"):
            yield no, line.replace(",", " ").split()


def _timestamp(token: str, path: Path, no: int) -> float:
    try:
        value = float(token)
    except ValueError:
        raise DynslamError(f"{path}:{no}: malformed line: timestamp {token!r} is not a number") from None
    if not np.isfinite(value):
        raise DynslamError(f"{path}:{no}: malformed line: timestamp {token!r} is not finite")
    return value


def check_increasing(entries: list[ListEntry], path: Path, what: str = "timestamp") -> None:
    """Timestamps of a list file must increase strictly from line to line (a repeat would drop a
    frame in the association, a step back would run frames out of order)."""
    for prev, cur in zip(entries, entries[1:], strict=False):
        if cur.timestamp > prev.timestamp:
            continue
        how = "repeats" if cur.timestamp == prev.timestamp else "is earlier than"
        raise DynslamError(f"{path}:{cur.line}: {what} {cur.stamp} {how} {prev.stamp} on line {prev.line}; "
                           f"the list must be sorted by time without repeats")


def read_file_list(path: Path) -> list[ListEntry]:
    """``rgb.txt`` / ``depth.txt``: ``timestamp filename`` per line."""
    path = Path(path)
    out = []
    for no, parts in _data_lines(path):
        if len(parts) != 2:
            raise DynslamError(f"{path}:{no}: malformed line: expected 'timestamp filename', "
                               f"got {len(parts)} fields")
        out.append(ListEntry(_timestamp(parts[0], path, no), parts[0], parts[1], no))
    if not out:
        raise DynslamError(f"{path} lists no images")
    check_increasing(out, path)
    return out


def read_associations(path: Path) -> list[tuple[ListEntry, ListEntry]]:
    """``associations.txt``: ``t_rgb rgb_file t_depth depth_file`` per line (the order of the two
    pairs is taken from the file names when the depth pair comes first)."""
    path = Path(path)
    out = []
    for no, parts in _data_lines(path):
        if len(parts) != 4:
            raise DynslamError(f"{path}:{no}: malformed line: expected 't_rgb rgb_file t_depth "
                               f"depth_file', got {len(parts)} fields")
        a = ListEntry(_timestamp(parts[0], path, no), parts[0], parts[1], no)
        b = ListEntry(_timestamp(parts[2], path, no), parts[2], parts[3], no)
        if a.file.startswith("depth") and not b.file.startswith("depth"):
            a, b = b, a
        out.append((a, b))
    if not out:
        raise DynslamError(f"{path} lists no image pairs")
    check_increasing([a for a, _ in out], path, "rgb timestamp")
    check_increasing([b for _, b in out], path, "depth timestamp")
    return out


def read_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A TUM trajectory file → (timestamps N, camera-to-world poses N×4×4), sorted by time; a
    repeated timestamp is an error."""
    path = Path(path)
    stamps, poses, lines = [], [], []
    for no, parts in _data_lines(path):
        if len(parts) != 8:
            raise DynslamError(f"{path}:{no}: malformed line: expected 'timestamp tx ty tz qx qy qz qw', "
                               f"got {len(parts)} fields")
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise DynslamError(f"{path}:{no}: malformed line: non-numeric value") from None
        if not all(np.isfinite(vals)):
            raise DynslamError(f"{path}:{no}: malformed line: non-finite value")
        q = np.array(vals[4:8])
        norm = float(np.linalg.norm(q))
        if norm < 1e-6:
            raise DynslamError(f"{path}:{no}: quaternion has zero length")
        T = np.eye(4)
        T[:3, :3] = quat_to_matrix(q / norm)
        T[:3, 3] = vals[1:4]
        stamps.append(vals[0])
        poses.append(T)
        lines.append((no, parts[0]))
    if not stamps:
        return np.zeros(0), np.zeros((0, 4, 4))
    t = np.asarray(stamps, dtype=np.float64)
    order = np.argsort(t, kind="stable")
    repeat = np.flatnonzero(np.diff(t[order]) == 0)
    if repeat.size:  # two poses at one time: which one holds is undefined
        (n0, s0), (n1, s1) = lines[order[repeat[0]]], lines[order[repeat[0] + 1]]
        raise DynslamError(f"{path}:{n1}: timestamp {s1} repeats {s0} on line {n0}; "
                           f"a trajectory holds one pose per time")
    return t[order], np.asarray(poses, dtype=np.float64)[order]


# --------------------------------------------------------------------------------------------
# rotations
def quat_to_matrix(q) -> np.ndarray:
    """Unit quaternion (x, y, z, w) → 3×3 rotation."""
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """3×3 rotation → unit quaternion (x, y, z, w) with w ≥ 0."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
    else:
        th = np.arccos(np.clip(d, -1.0, 1.0))
        q = (np.sin((1 - a) * th) * q0 + np.sin(a * th) * q1) / np.sin(th)
    return q / np.linalg.norm(q)


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(slerp(matrix_to_quat(T0[:3, :3]), matrix_to_quat(T1[:3, :3]), a))
    T[:3, 3] = (1 - a) * T0[:3, 3] + a * T1[:3, 3]
    return T


# --------------------------------------------------------------------------------------------
# association
def associate(first, second, max_diff: float) -> list[tuple[int, int]]:
    """One-to-one association of two timestamp lists (TUM ``associate.py`` semantics).

    Candidates are pairs with ``|a - b| < max_diff``; they are taken in order of increasing
    difference (ties: lower indices first), skipping any whose timestamps are already used.
    Returns index pairs ``(i, j)`` sorted by ``i``.
    """
    a = np.asarray(first, dtype=np.float64)
    b = np.asarray(second, dtype=np.float64)
    if a.size == 0 or b.size == 0:
        return []
    order = np.argsort(b, kind="stable")
    bs = b[order]
    lo = np.searchsorted(bs, a - max_diff, side="left")
    hi = np.searchsorted(bs, a + max_diff, side="right")
    cands = []
    for i in range(a.size):
        for k in range(lo[i], hi[i]):
            d = abs(a[i] - bs[k])
            if d < max_diff:
                cands.append((d, i, int(order[k])))
    cands.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    pairs.sort()
    return pairs


def poses_at(times, gt_times: np.ndarray, gt_poses: np.ndarray, max_diff: float,
             interpolate: bool = True) -> list[np.ndarray | None]:
    """Ground-truth pose at each of ``times`` (see the module docstring for the rule)."""
    out: list[np.ndarray | None] = []
    n = len(gt_times)
    for t in np.asarray(times, dtype=np.float64):
        if n == 0:
            out.append(None)
            continue
        k = int(np.searchsorted(gt_times, t, side="left"))  # gt_times[k-1] < t <= gt_times[k]
        prev = k - 1 if k > 0 else None
        nxt = k if k < n else None
        d_prev = t - gt_times[prev] if prev is not None else np.inf
        d_next = gt_times[nxt] - t if nxt is not None else np.inf
        if min(d_prev, d_next) > max_diff:
            out.append(None)
        elif d_next == 0.0:
            out.append(gt_poses[nxt].copy())
        elif (interpolate and prev is not None and nxt is not None
              and gt_times[nxt] - gt_times[prev] <= 2 * max_diff):
            a = float(d_prev / (gt_times[nxt] - gt_times[prev]))
            out.append(interpolate_pose(gt_poses[prev], gt_poses[nxt], a))
        else:
            out.append(gt_poses[prev if d_prev <= d_next else nxt].copy())
    return out


# --------------------------------------------------------------------------------------------
# the reader
def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG header without decoding; None when not a PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) == 24 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    return None


def image_size(path: Path, where: str = "") -> tuple[int, int]:
    size = png_size(path)
    if size is not None:
        return size
    import cv2

    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise DynslamError(f"cannot decode image {path}{f' ({where})' if where else ''}: not a readable image file")
    return img.shape[1], img.shape[0]


def read_synth_json(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DynslamError(f"cannot read {path}: {exc}") from None
    if not isinstance(meta, dict):
        raise DynslamError(f"{path} must hold a JSON object")
    return meta


def _intrinsic_values(cfg_intr, folder: Path, meta: dict | None) -> tuple[list[float], str]:
    if cfg_intr is not None:
        vals, source = cfg_intr, "config key data.intrinsics"
    elif meta is not None and meta.get("intrinsics") is not None:
        vals, source = meta["intrinsics"], str(folder / "synth.json") + " 'intrinsics'"
    else:
        raise DynslamError(
            f"no camera intrinsics for {folder}: set data.intrinsics=[fx,fy,cx,cy] "
            f"(--set or --config), or name the dataset (tum/…, bonn/…) so configs/ supplies them")
    if isinstance(vals, dict):
        vals = [vals.get(k) for k in ("fx", "fy", "cx", "cy")]
    try:
        vals = [float(v) for v in vals]
    except (TypeError, ValueError):
        raise DynslamError(f"intrinsics from {source} must be 4 numbers fx, fy, cx, cy, got {vals!r}") from None
    if len(vals) != 4 or vals[0] <= 0 or vals[1] <= 0:
        raise DynslamError(f"intrinsics from {source} must be 4 numbers fx, fy, cx, cy with fx, fy > 0, got {vals!r}")
    return vals, source


def _distortion_values(cfg_dist) -> list[float]:
    if cfg_dist is None:
        return [0.0] * 5
    try:
        vals = [float(v) for v in cfg_dist]
    except (TypeError, ValueError):
        raise DynslamError(f"config key data.distortion must be numbers k1, k2, p1, p2[, k3], got {cfg_dist!r}") from None
    if len(vals) not in (4, 5, 8, 12, 14):
        raise DynslamError(f"config key data.distortion must have 4, 5, 8, 12 or 14 coefficients "
                           f"(OpenCV order), got {len(vals)}")
    return vals


def cut_indices(n: int, start: int, frames: int, stride: int, where: str) -> list[int]:
    """Indices kept by the start/frames/stride cut of ``n`` associated pairs."""
    if stride < 1:
        raise DynslamError(f"data.stride must be ≥ 1, got {stride}")
    if start < 0:
        raise DynslamError(f"data.start must be ≥ 0, got {start}")
    if frames < 0:
        raise DynslamError(f"data.frames must be ≥ 0 (0 = all), got {frames}")
    if start >= n:
        raise DynslamError(f"data.start={start} is past the end of {where} ({n} frames)")
    idx = list(range(start, n, stride))
    return idx[:frames] if frames else idx


def read_folder(folder: Path, cfg, *, dataset: str, name: str, spec: str) -> Sequence:
    """Open a TUM-layout folder (TUM, Bonn or synthetic) with the data settings of ``cfg``."""
    from dynslam_cli.data.undistort import Undistorter, has_distortion

    folder = Path(folder)
    dc = cfg.data
    if not folder.is_dir():
        raise DynslamError(f"sequence folder {folder} does not exist")
    max_diff = float(dc.max_time_diff)
    if max_diff <= 0:
        raise DynslamError(f"data.max_time_diff must be > 0, got {max_diff}")

    assoc_file = folder / "associations.txt"
    if assoc_file.is_file():
        pairs = read_associations(assoc_file)
        source = str(assoc_file)
    else:
        rgb_file, depth_file = folder / "rgb.txt", folder / "depth.txt"
        if not rgb_file.is_file():
            raise DynslamError(f"{rgb_file} not found: {folder} is not a TUM-layout sequence folder "
                               f"(rgb.txt, depth.txt[, groundtruth.txt])")
        rgb = read_file_list(rgb_file)
        depth = read_file_list(depth_file)
        idx = associate([e.timestamp for e in rgb], [e.timestamp for e in depth], max_diff)
        if not idx:
            raise DynslamError(
                f"no rgb/depth timestamps of {rgb_file} and {depth_file} associate within "
                f"data.max_time_diff={max_diff:g} s (rgb {rgb[0].timestamp:.6f}…{rgb[-1].timestamp:.6f}, "
                f"depth {depth[0].timestamp:.6f}…{depth[-1].timestamp:.6f})")
        pairs = [(rgb[i], depth[j]) for i, j in idx]
        source = f"{rgb_file} and {depth_file}"
        for (r0, d0), (r1, d1) in zip(pairs, pairs[1:], strict=False):
            if d1.timestamp <= d0.timestamp:  # only with a max_time_diff wider than the frame interval
                raise DynslamError(
                    f"{depth_file}:{d1.line}: depth {d1.stamp} pairs with rgb {r1.stamp} ({rgb_file} line "
                    f"{r1.line}) but depth {d0.stamp} (line {d0.line}) with the earlier rgb {r0.stamp}: the "
                    f"association runs backwards; lower data.max_time_diff={max_diff:g}")

    keep = cut_indices(len(pairs), int(dc.start), int(dc.frames), int(dc.stride), source)
    pairs_cut = [pairs[k] for k in keep]

    # listed files must exist
    for r, d in pairs_cut:
        for entry, kind in ((r, "rgb"), (d, "depth")):
            if not (folder / entry.file).is_file():
                where = source if assoc_file.is_file() else str(folder / f"{kind}.txt")
                raise DynslamError(f"{kind} image {folder / entry.file} listed in {where} "
                                   f"(line {entry.line}) is missing")

    # ground truth
    gt_file = folder / "groundtruth.txt"
    gt_file = gt_file if gt_file.is_file() else None
    if gt_file is not None:
        gt_t, gt_T = read_trajectory(gt_file)
        poses = poses_at([r.timestamp for r, _ in pairs_cut], gt_t, gt_T, max_diff, interpolate=True)
    else:
        poses = [None] * len(pairs_cut)

    # synthetic extras
    meta_file = folder / "synth.json"
    meta = read_synth_json(meta_file) if meta_file.is_file() else None
    depth_scale = float(dc.depth_scale)
    if meta is not None and meta.get("depth_scale") is not None:
        try:
            depth_scale = float(meta["depth_scale"])
        except (TypeError, ValueError):
            raise DynslamError(f"{meta_file}: 'depth_scale' must be a number") from None
    if depth_scale <= 0:
        raise DynslamError(f"depth scale must be > 0, got {depth_scale}")
    depth_noise = float(dc.DEPTH_NOISE)
    sensor = meta.get("sensor") if meta is not None else None
    if isinstance(sensor, dict) and sensor.get("depth_noise") is not None:  # the renderer's own noise model
        try:
            depth_noise = float(sensor["depth_noise"])
        except (TypeError, ValueError):
            raise DynslamError(f"{meta_file}: 'sensor.depth_noise' must be a number") from None
        if not depth_noise > 0:  # a noiseless render: depth trusted to a tenth of a millimetre per metre^2
            depth_noise = 1e-4

    def label_paths(sub: str) -> list[Path] | None:
        d = folder / sub
        if not d.is_dir():
            return None
        out = []
        for r, _ in pairs_cut:
            cands = [d / (Path(r.file).stem + ".png"), d / (r.stamp + ".png")]
            found = next((c for c in cands if c.is_file()), None)
            if found is None:
                raise DynslamError(f"{sub} image for frame at {r.stamp} is missing: {cands[0]}")
            out.append(found)
        return out

    inst_paths = label_paths("instances")
    dyn_paths = label_paths("dynamic")

    # camera
    intr_vals, _ = _intrinsic_values(dc.intrinsics, folder, meta)
    width, height = image_size(folder / pairs_cut[0][0].file, f"frame 0 of {name}")
    intr = Intrinsics(*intr_vals, width=int(width), height=int(height))
    distortion = _distortion_values(dc.distortion)
    undistorter = None
    if has_distortion(distortion):  # rgb and depth are undistorted whenever the distortion is non-zero
        undistorter = Undistorter(intr.K, distortion, width, height)

    records = [
        FrameRecord(timestamp=r.timestamp, rgb=folder / r.file, depth=folder / d.file, pose_c2w=p,
                    instances=inst_paths[n] if inst_paths else None,
                    dynamic=dyn_paths[n] if dyn_paths else None, source_index=k, stamp=r.stamp)
        for n, ((r, d), p, k) in enumerate(zip(pairs_cut, poses, keep, strict=False))
    ]
    return Sequence(name=name, dataset=dataset, path=folder, spec=spec, intrinsics=intr,
                    distortion=distortion, records=records, depth_scale=depth_scale,
                    max_depth=float(dc.max_depth), depth_noise=depth_noise, groundtruth_file=gt_file,
                    undistorter=undistorter, has_gt_masks=dyn_paths is not None,
                    has_instances=inst_paths is not None, total_pairs=len(pairs))
