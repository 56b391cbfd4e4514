"""Local bundle adjustment with gtsam: the poses of a window of keyframes and the landmarks they
see, keyframes outside the window that also see those landmarks held fixed, RGB-D stereo factors
(``GenericStereoFactor3D`` with the covariance of independent pixel and depth noise, the depth's
noise binned on a log scale so factors share noise models; a projection factor where a keypoint
had no depth) under a Huber
kernel, Levenberg-Marquardt with a bounded number of iterations; then the observations over the
chi-square gate are dropped and it runs once more (ORB-SLAM's two passes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dynslam_cli.backend.features import SCALE
from dynslam_cli.backend.tracking import CHI2_MONO, CHI2_STEREO, Camera, information, whitened_chi2


@dataclass
class BundleResult:
    """``poses``: the optimised keyframes' new camera-to-world poses; ``ids``/``pos``: the
    landmarks' new world positions; ``outlier``: bool over the observations passed in (those
    used and over the gate after the last pass); ``cost0``/``cost``: the robust cost before/after;
    ``ms``: wall time."""

    poses: dict
    ids: np.ndarray
    pos: np.ndarray
    outlier: np.ndarray
    cost0: float
    cost: float
    ms: float


def observation_chi2(cam: Camera, Tcw: np.ndarray, X: np.ndarray, uv: np.ndarray, depth: np.ndarray,
                     octave: np.ndarray, dsig: np.ndarray) -> np.ndarray:
    """Whitened squared residual of each observation: camera ``Tcw[i]`` (world-to-camera, M×4×4)
    sees world point ``X[i]`` at ``uv[i]`` with ``depth[i]`` (0 = none) of standard deviation ``dsig[i]``."""
    pc = np.einsum("mij,mj->mi", Tcw[:, :3, :3], X) + Tcw[:, :3, 3]
    return whitened_chi2(cam, pc, uv, depth, octave, dsig)


def local_bundle_adjustment(cam: Camera, poses: dict, optimise, fixed, ids: np.ndarray, pos: np.ndarray,
                            obs_kf: np.ndarray, obs_lm: np.ndarray, obs_uv: np.ndarray, obs_depth: np.ndarray,
                            obs_octave: np.ndarray, obs_dsig: np.ndarray, huber: float, iters: tuple = (5, 10)) -> BundleResult:
    """Optimise keyframes ``optimise`` (ids into ``poses``: camera-to-world 4×4) and landmarks
    ``ids`` (world positions ``pos``), keyframes ``fixed`` held where they are.  Observations
    (``obs_*``) of other keyframes or landmarks are ignored.  ``huber``: kernel width in pixels
    (its square scaled is the chi-square gate)."""
    import time

    import gtsam

    t0 = time.perf_counter()
    optimise = [int(k) for k in optimise]
    fixed = [int(k) for k in fixed if int(k) not in set(optimise)]
    if not fixed:  # the gauge: hold the first keyframe of the window
        fixed, optimise = optimise[:1], optimise[1:]
    kfs = np.asarray(optimise + fixed, np.int64)
    row = np.full(int(max(ids.max(initial=-1), obs_lm.max(initial=-1))) + 1, -1, np.int64)
    row[ids] = np.arange(len(ids))
    use = np.isin(obs_kf, kfs) & (obs_lm < len(row))
    use[use] = row[obs_lm[use]] >= 0
    sel = np.flatnonzero(use)
    # a landmark observed once in the window constrains no pose: it is left out of the graph and
    # moves rigidly with its keyframe (its optimum), which makes the graph several times smaller
    n_seen = np.bincount(row[obs_lm[sel]], minlength=len(ids))
    multi = n_seen >= 2
    X = lambda k: gtsam.symbol("x", int(k))  # noqa: E731
    L = lambda j: gtsam.symbol("l", int(j))  # noqa: E731
    Kst = gtsam.Cal3_S2Stereo(cam.fx, cam.fy, 0.0, cam.cx, cam.cy, cam.bf / cam.fx)
    Km = gtsam.Cal3_S2(cam.fx, cam.fy, 0.0, cam.cx, cam.cy)
    th = huber
    th_m = huber * np.sqrt(CHI2_MONO / CHI2_STEREO)
    huber_s = gtsam.noiseModel.mEstimator.Huber.Create(th)
    huber_m = gtsam.noiseModel.mEstimator.Huber.Create(th_m)
    models = {}

    def noise_s(o, sd):
        """(u_L, u_R, v) with u_R = u - disparity: the pixel's and the disparity's noise (sd px) independent."""
        key = (int(o), int(round(np.log(sd) * 16)))
        if key not in models:
            s2, t2 = SCALE ** (2.0 * o), float(np.exp(key[1] / 16.0)) ** 2
            cov = np.array([[s2, s2, 0.0], [s2, s2 + t2, 0.0], [0.0, 0.0, s2]])
            models[key] = gtsam.noiseModel.Robust.Create(huber_s, gtsam.noiseModel.Gaussian.Covariance(cov))
        return models[key]

    noise_m = [gtsam.noiseModel.Robust.Create(huber_m, gtsam.noiseModel.Isotropic.Sigma(2, SCALE ** o))
               for o in range(16)]
    anchor = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)

    values = gtsam.Values()
    for k in kfs:
        values.insert(X(k), gtsam.Pose3(np.asarray(poses[int(k)], np.float64)))
    for j, p in zip(ids[multi], pos[multi], strict=False):
        values.insert(L(j), np.asarray(p, np.float64))
    in_graph = multi[row[obs_lm[sel]]]
    factors = {}
    oct_ = np.clip(obs_octave[sel], 0, 15)
    info = information(cam, obs_depth[sel], obs_dsig[sel], obs_octave[sel])
    sd_px = 1.0 / np.sqrt(np.maximum(info[:, 2], 1e-12))
    for i in np.flatnonzero(in_graph):
        k, j, (u, v), d, o = obs_kf[sel[i]], obs_lm[sel[i]], obs_uv[sel[i]], obs_depth[sel[i]], oct_[i]
        if d > 0:
            f = gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(u, u - cam.bf / d, v), noise_s(o, sd_px[i]), X(k), L(j),
                                            Kst)
        else:
            f = gtsam.GenericProjectionFactorCal3_S2(np.array([u, v]), noise_m[o], X(k), L(j), Km)
        factors[i] = f
    ordering = gtsam.Ordering()
    for j in ids[multi]:
        ordering.push_back(L(j))
    for k in kfs:
        ordering.push_back(X(k))

    def solve(active, values, n_iter):
        graph = gtsam.NonlinearFactorGraph()
        for k in fixed:
            graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(np.asarray(poses[k], np.float64)), anchor))
        for i in np.flatnonzero(active & in_graph):
            graph.add(factors[i])
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(int(n_iter))
        params.setOrdering(ordering)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        e0 = graph.error(values)
        out = opt.optimize()
        return out, e0, graph.error(out)

    kf_row = np.full(int(kfs.max()) + 1, -1, np.int64)
    kf_row[kfs] = np.arange(len(kfs))
    obs_row = kf_row[obs_kf[sel]]
    T_old = np.stack([np.asarray(poses[int(k)], np.float64) for k in kfs])
    single_kf = np.zeros(len(ids), np.int64)  # the keyframe row of each single observation
    single_kf[row[obs_lm[sel]][~in_graph]] = obs_row[~in_graph]

    def positions(values):
        T_new = np.stack([values.atPose3(X(k)).matrix() for k in kfs])
        out = np.empty_like(np.asarray(pos, np.float64))
        if multi.any():
            out[multi] = np.stack([values.atPoint3(L(j)) for j in ids[multi]])
        if (~multi).any():  # X' = T_new T_old^-1 X, with the keyframe each was seen from
            M = T_new[single_kf[~multi]] @ np.linalg.inv(T_old[single_kf[~multi]])
            out[~multi] = np.einsum("mij,mj->mi", M[:, :3, :3], pos[~multi]) + M[:, :3, 3]
        return T_new, out

    def gate(values):
        T_new, Xs = positions(values)
        c2 = observation_chi2(cam, np.linalg.inv(T_new)[obs_row], Xs[row[obs_lm[sel]]], obs_uv[sel],
                              obs_depth[sel], obs_octave[sel], obs_dsig[sel])
        return c2 > np.where(obs_depth[sel] > 0, th ** 2, th_m ** 2)

    active = np.ones(len(sel), bool)
    values, cost0, cost = solve(active, values, iters[0])
    bad = gate(values)
    if bad.any() and len(iters) > 1:
        values, _, cost = solve(~bad, values, iters[1])
        bad = gate(values)
    outlier = np.zeros(len(obs_kf), bool)
    outlier[sel[bad]] = True
    new_poses = {k: values.atPose3(X(k)).matrix() for k in optimise}
    new_pos = positions(values)[1]
    return BundleResult(new_poses, np.asarray(ids), new_pos, outlier, float(cost0), float(cost),
                        (time.perf_counter() - t0) * 1000)
