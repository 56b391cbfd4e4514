"""Mesh extraction: marching cubes (scikit-image) at SDF level 0 over the observed volume,
vertices coloured by the colour decoder."""

from __future__ import annotations

import math

import numpy as np
import torch

from dynslam_cli.errors import DynslamError


@torch.no_grad()
def query(model, pts: np.ndarray, device, color: bool = False, chunk: int = 1 << 16) -> np.ndarray:
    """The map at world points ``pts`` (N, 3), in chunks: SDF (N,) or, with ``color``, RGB (N, 3)."""
    out = np.empty((len(pts), 3) if color else len(pts), np.float32)
    for i in range(0, len(pts), chunk):
        p = torch.from_numpy(np.ascontiguousarray(pts[i:i + chunk], dtype=np.float32)).to(device)
        sdf, rgb = model(p, color=color)
        out[i:i + chunk] = (rgb if color else sdf).cpu().numpy()
    return out


def extract_mesh(model, observed_pts: np.ndarray, voxel: float, device, dilate_m: float | None = None):
    """Mesh of the zero level set near ``observed_pts`` (world points seen by the camera).

    Only voxels within ``dilate_m`` (default: 2 truncations) of an observed point are meshed, so
    never-seen space (where the map is arbitrary) makes no surface."""
    import trimesh
    from scipy import ndimage
    from skimage import measure

    if voxel <= 0:
        raise DynslamError(f"mesh voxel size must be > 0, got {voxel}")
    if observed_pts is None or len(observed_pts) == 0:
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int64))
    dilate_m = 2 * model.truncation if dilate_m is None else dilate_m
    b = model.bounds
    lo = np.maximum(observed_pts.min(0) - dilate_m, b[0])
    hi = np.minimum(observed_pts.max(0) + dilate_m, b[1])
    if np.any(hi <= lo):
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int64))
    dims = np.maximum(np.ceil((hi - lo) / voxel).astype(int) + 1, 2)
    if int(np.prod(dims)) > 400_000_000:
        raise DynslamError(f"mesh grid {tuple(dims)} too large for voxel {voxel} m; use a larger run.mesh_resolution")
    occ = np.zeros(dims, bool)
    ijk = np.clip(np.round((observed_pts - lo) / voxel).astype(int), 0, dims - 1)
    occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    r = max(1, int(math.ceil(dilate_m / voxel)))
    occ = ndimage.binary_dilation(occ, structure=ndimage.generate_binary_structure(3, 1), iterations=r)
    xs = [lo[k] + np.arange(dims[k]) * voxel for k in range(3)]
    sdf = np.ones(dims, np.float32)
    # query only voxels near observations
    idx = np.nonzero(occ)
    pts = np.stack([xs[0][idx[0]], xs[1][idx[1]], xs[2][idx[2]]], -1)
    sdf[idx] = query(model, pts, device)
    if not (sdf.min() < 0 < sdf.max()):
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int64))
    verts, faces, _, _ = measure.marching_cubes(sdf, level=0.0, spacing=(voxel,) * 3, mask=occ)
    verts = verts + lo
    rgb = query(model, verts, device, color=True)
    colors = np.concatenate([(rgb * 255).clip(0, 255).astype(np.uint8), np.full((len(verts), 1), 255, np.uint8)], 1)
    return trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colors, process=False)


def drop_vertices(mesh, drop: np.ndarray):
    """``mesh`` without the vertices ``drop`` (bool, one per vertex), the faces that use them and the
    vertices left without a face."""
    import trimesh

    drop = np.asarray(drop, bool)
    if not drop.any():
        return mesh
    keep_f = ~drop[np.asarray(mesh.faces)].any(1) if len(mesh.faces) else np.zeros(0, bool)
    faces = np.asarray(mesh.faces)[keep_f]
    used = np.zeros(len(mesh.vertices), bool)
    used[faces.ravel()] = True
    new_index = np.cumsum(used) - 1
    colors = mesh.visual.vertex_colors[used] if mesh.visual.kind == "vertex" else None
    return trimesh.Trimesh(vertices=np.asarray(mesh.vertices)[used], faces=new_index[faces],
                           vertex_colors=colors, process=False)
