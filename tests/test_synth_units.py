"""Units of the synthetic renderer: sensor model, textures, ray casting, cameras, walkers."""

from __future__ import annotations

import numpy as np
import pytest

import dynslam_cli.config  # noqa: F401  (import order: config before synth.config)
from dynslam_cli.synth import sensor, textures
from dynslam_cli.synth.geometry import Parts, camera_rotation, rot_to_quat
from dynslam_cli.synth.render import _Arrays, intrinsics_for
from dynslam_cli.synth.scene import ROOM_MAX, ROOM_MIN, build_scene

# ----------------------------------------------------------------------------- sensor


def test_depth_noise_grows_with_depth_squared():
    rng = np.random.default_rng(0)
    for z in (1.0, 2.0, 4.0):
        d = np.full((200, 200), z)
        q = sensor.sense_depth(d, rng, 0.002, 0.0, True).astype(np.float64) / 5000
        assert (q > 0).all()  # a flat wall has no edge holes
        assert np.std(q - z) == pytest.approx(0.002 * z * z, rel=0.1)
        assert abs(np.mean(q - z)) < 0.002 * z * z / 20


def test_depth_quantised_and_exact_without_noise():
    d = np.linspace(0.5, 5.0, 64 * 48).reshape(48, 64)
    q = sensor.sense_depth(d, np.random.default_rng(0), 0.0, 0.0, False)
    assert q.dtype == np.uint16
    assert np.array_equal(q, np.round(d * 5000).astype(np.uint16))


def test_random_holes_and_range_holes():
    d = np.full((300, 300), 2.0)
    d[:10] = 0.1  # closer than the sensor's minimum range
    q = sensor.sense_depth(d, np.random.default_rng(1), 0.0, 0.05, False)
    assert (q[:10] == 0).all()
    assert (q[10:] == 0).mean() == pytest.approx(0.05, abs=0.01)


def test_edge_holes_on_far_side_of_discontinuities_only():
    d = np.full((40, 60), 3.0)
    d[:, :30] = 1.0  # a near object on the left
    mask = sensor.edge_hole_mask(d, fx=525.0)
    assert mask[:, 30].all() and not mask[:, 29].any()
    assert mask.sum() == 40
    # A slanted plane (floor seen at a grazing angle) is not cut, even at low resolution.
    fx = 52.5
    v = np.arange(48)[:, None] - 23.5
    floor = np.where(v > 2, 1.4 * fx / np.maximum(v, 1e-6), 6.0) * np.ones((1, 64))
    floor = np.minimum(floor, 6.0)
    assert not sensor.edge_hole_mask(floor[5:], fx=fx)[5:].any()


def test_rgb_noise():
    img = np.full((100, 100, 3), 128.0, np.float32)
    out = sensor.sense_rgb(img, np.random.default_rng(0), 3.0)
    assert out.dtype == np.uint8 and np.std(out.astype(float)) == pytest.approx(3.0, rel=0.1)
    assert np.array_equal(sensor.sense_rgb(img, np.random.default_rng(0), 0.0), img.astype(np.uint8))


# ----------------------------------------------------------------------------- textures


def test_value_noise_tiles_seamlessly_and_has_detail():
    n = textures.value_noise(np.random.default_rng(0), 256)
    inner = np.abs(np.diff(n, axis=0)).mean()
    seam = np.abs(n[0] - n[-1]).mean()
    assert seam < 2 * inner
    assert n.min() >= 0 and n.max() <= 1 and n.std() > 0.1


@pytest.mark.parametrize("maker", ["wall", "tiles", "planks", "ceiling", "fabric", "skin", "painted", "ball",
                                   "cardboard"])
def test_textures_are_textured(maker):
    img = getattr(textures, maker)(np.random.default_rng(0))
    assert img.shape == (textures.SIZE, textures.SIZE, 3) and img.dtype == np.uint8
    gray = img.astype(float).mean(axis=2)
    # Texture at fine scale (neighbouring texels differ) and at coarse scale.
    assert np.abs(np.diff(gray, axis=1)).mean() > 0.5
    assert gray.std() > 5


# ----------------------------------------------------------------------------- ray casting


def _cast(arrays: _Arrays, R, c, w=33, h=25, f=20.0):
    from dynslam_cli.synth.raycast import raycast

    tex = np.full((1, 4, 4, 3), 200, np.uint8)
    return raycast(R, np.asarray(c, float), f, f, (w - 1) / 2, (h - 1) / 2, w, h, *arrays.pack(), tex,
                   np.array([0.0, 0.0, 2.5]), 0.35)


def test_raycast_depth_matches_analytic_geometry():
    R = camera_rotation(0.0, 0.0, 0.0)  # looking along +x, z up
    a = _Arrays()
    room = Parts().box((0, 0, 1.35), (2.5, 2.0, 1.35), tex=0)
    a.add(room, 0, inside=True, bound=False)
    a.add(Parts().ellipsoid((1.5, 0.0, 1.0), (0.5, 0.5, 0.5), tex=0), 7)
    a.add(Parts().box((2.0, 0.8, 1.0), (0.1, 0.1, 0.1), tex=0), 8)
    depth, inst, rgb = _cast(a, R, (0.0, 0.0, 1.0))
    assert inst[12, 16] == 7 and depth[12, 16] == pytest.approx(1.0, abs=1e-9)
    # Corner pixel: the ray hits the room's wall x = 2.5 (z-depth 2.5) or the floor/ceiling/side.
    assert inst[0, 0] == 0 and depth[0, 0] > 0
    # The box at (2, 0.8, 1) is left of the axis (x_cam = -y/x = -0.4): its front face x = 1.9.
    u = int(round(16 + 20 * (-0.8 / 2.0)))
    assert inst[12, u] == 8 and depth[12, u] == pytest.approx(1.9, abs=1e-9)
    # The sphere's silhouette: points on it satisfy |p - c| = r.
    v, uu = np.nonzero(inst == 7)
    z = depth[v, uu]
    pc = np.stack([(uu - 16) / 20 * z, (v - 12) / 20 * z, z], axis=1)
    pw = pc @ R.T + np.array([0.0, 0.0, 1.0])
    assert np.allclose(np.linalg.norm(pw - [1.5, 0, 1.0], axis=1), 0.5, atol=1e-9)
    assert (rgb[inst == 7] > 0).all() and (rgb <= 255).all()


def test_raycast_culling_does_not_change_the_image():
    """Groups culled per tile give the same image as testing every primitive."""
    scene = build_scene("crowd", 0, 20, 30.0, intrinsics_for(64, 48), 64, 48)
    from dynslam_cli.synth.raycast import raycast

    culled, flat = _Arrays(), _Arrays()
    culled.add(scene.room, 0, inside=True, bound=False)
    flat.add(scene.room, 0, inside=True, bound=False)
    for o in scene.statics:
        culled.add(o.parts, o.id)
        flat.add(o.parts, o.id, bound=False)
    for m in scene.movers:
        culled.add(m.at(0.6), m.id)
        flat.add(m.at(0.6), m.id, bound=False)
    R, c = scene.camera(0.6)
    fx, fy, cx, cy = intrinsics_for(64, 48)
    out = [raycast(R, c, fx, fy, cx, cy, 64, 48, *a.pack(), scene.textures, scene.light, scene.ambient)
           for a in (culled, flat)]
    assert np.array_equal(out[0][1], out[1][1])
    assert np.array_equal(out[0][0], out[1][0])


# ----------------------------------------------------------------------------- cameras, walkers


def test_intrinsics_scale_with_size():
    assert intrinsics_for(640, 480) == (525.0, 525.0, 319.5, 239.5)
    assert intrinsics_for(320, 240) == (262.5, 262.5, 159.5, 119.5)


def test_quaternion_round_trip():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    for _ in range(50):
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        q = rot_to_quat(R)
        assert np.allclose(Rotation.from_quat(q).as_matrix(), R, atol=1e-9) and q[3] >= 0


@pytest.mark.parametrize("preset", ["static", "walker", "kidnap", "balloon"])
def test_hand_held_camera_moves_like_a_person(preset):
    n, fps = 150, 30.0
    scene = build_scene(preset, 0, n, fps, intrinsics_for(64, 48), 64, 48)
    poses = [scene.camera(i / fps) for i in range(n)]
    R = np.array([p[0] for p in poses])
    c = np.array([p[1] for p in poses])
    assert np.allclose(np.einsum("nij,nik->njk", R, R), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert (R[:, 2, 1] < -0.9).all()  # camera y axis points down (z up world): OpenCV convention
    assert ((c > ROOM_MIN + 0.3) & (c < ROOM_MAX - 0.3)).all()
    assert (1.2 <= c[:, 2]).all() and (c[:, 2] <= 1.75).all()
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert 0.8 <= step.sum() <= 2.5  # ~1-2 m over 150 frames
    assert step.max() < 0.04
    yaw = np.unwrap(np.arctan2(R[:, 1, 2], R[:, 0, 2]))
    ang = np.degrees(np.arccos(np.clip((np.einsum("nij,nij->n", R[1:], R[:-1]) - 1) / 2, -1, 1)))
    assert np.degrees(yaw.max() - yaw.min()) > 8 and ang.max() < 2.0
    # A small high-frequency shake: the second difference is not that of a smooth curve.
    jerk = np.linalg.norm(np.diff(c, 2, axis=0), axis=1)
    assert jerk.mean() > 1e-4


def test_walker_is_person_sized_and_walks_on_the_floor():
    scene = build_scene("walker", 0, 60, 30.0, intrinsics_for(64, 48), 64, 48)
    (w,) = scene.movers
    centres = []
    for i in range(0, 60, 5):
        box = w.at(i / 30).aabb()
        assert 1.55 < box[1, 2] < 1.95 and -0.08 < box[0, 2] < 0.1
        assert 0.3 < box[1, 0] - box[0, 0] < 1.2 and 0.3 < box[1, 1] - box[0, 1] < 1.2
        centres.append(box.mean(axis=0)[:2])
    speed = np.linalg.norm(np.diff(centres, axis=0), axis=1) / (5 / 30)
    assert speed.max() < 2.0 and speed[len(speed) // 2:].mean() > 0.5  # human walking speeds
