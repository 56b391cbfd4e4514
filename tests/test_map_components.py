import numpy as np
import torch

from dynslam_cli.config import Config
from dynslam_cli.map.encoding import OneBlob
from dynslam_cli.map.mesh import drop_vertices
from dynslam_cli.map.losses import sdf_free_losses
from dynslam_cli.map.render import sample_depths, sdf_weights


def test_oneblob_values_and_gradient():
    enc = OneBlob(4, 3)
    x = torch.tensor([[0.125, 0.5, 0.9]], requires_grad=True)
    out = enc(x).view(3, 4)
    vals = out.detach()
    centres = (np.arange(4) + 0.5) / 4
    expect = np.exp(-((x.detach().numpy().reshape(3, 1) - centres) ** 2) * 0.5 * 16)
    assert np.allclose(out.detach().numpy(), expect, atol=1e-6)
    assert vals[0].argmax() == 0 and vals[2].argmax() == 3 and abs(float(vals[0, 0]) - 1.0) < 1e-6
    out.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_oneblob_without_gradient_gives_the_same_bits_and_leaves_x_alone():
    enc = OneBlob(16, 3)
    x = torch.rand(5000, 3, generator=torch.Generator().manual_seed(0)) * 1.4 - 0.2  # some outside [0, 1]
    x0 = x.clone()
    with_grad = enc(x.clone().requires_grad_(True)).detach()
    without = enc(x)  # the in-place path
    assert torch.equal(without, with_grad) and torch.equal(x, x0)
    with torch.no_grad():
        assert torch.equal(enc(x.clone().requires_grad_(True)), with_grad)


def test_weights_peak_at_the_surface():
    z = torch.linspace(0.5, 1.5, 41)[None]
    tr = 0.1
    sdf = (1.0 - z) / tr  # surface at z = 1
    w = sdf_weights(sdf, z, tr)
    assert abs(float(z[0, w.argmax()]) - 1.0) < 0.03
    assert abs(float(w.sum()) - 1.0) < 1e-5
    assert float(w[0, z[0] > 1.0 + tr + 1e-6].sum()) == 0.0  # nothing behind the first surface + tr
    assert abs(float((w * z).sum()) - 1.0) < 0.01  # sharp weights: the rendered depth is the surface
    # free-space samples (sdf = 1 truncation) get almost no weight
    wf = sdf_weights(torch.tensor([[1.0, 1.0, 0.2, -0.2]]), torch.tensor([[0.5, 0.7, 0.98, 1.02]]), tr)
    assert float(wf[0, :2].sum()) < 1e-3


def test_depth_guided_sampling_bands_and_missing_depth():
    cfg = Config().map
    d = torch.tensor([2.0, 0.0, 1.0])
    z = sample_depths(d, cfg, torch.Generator().manual_seed(0))
    S = cfg.SAMPLES_FREE + cfg.samples_surface
    assert z.shape == (3, S)
    band = z[0, cfg.SAMPLES_FREE:]
    assert torch.all((band >= 2.0 - cfg.surface_range) & (band <= 2.0 + cfg.surface_range))
    assert torch.all(z[0, :cfg.SAMPLES_FREE] <= 2.0 - cfg.surface_range) and torch.all(z[0] >= cfg.near)
    assert torch.all((z[1] >= cfg.near) & (z[1] <= cfg.far)) and float(z[1].max()) > 0.8 * cfg.far
    assert torch.all(z[:, 1:] >= z[:, :-1])


def test_sdf_and_free_space_losses_vanish_for_the_true_sdf():
    tr = 0.1
    z = torch.linspace(0.2, 1.3, 30)[None]
    d = torch.tensor([1.0])
    true = ((d[:, None] - z) / tr).clamp(-1, 1)
    free, sdf = sdf_free_losses(z, d, true, tr)
    assert float(free) < 1e-12 and float(sdf) < 1e-12
    free2, sdf2 = sdf_free_losses(z, d, true + 0.5, tr)
    assert float(sdf2) > 1e-4 and float(free2) > 1e-4


def _small_map():
    """A 4-level map over a 2 m cube with a random table, and 64 points in it."""
    from dynslam_cli.map.model import NeuralMap

    torch.manual_seed(0)
    cfg = Config().map
    cfg.n_levels, cfg.log2_hashmap_size = 4, 10
    m = NeuralMap(cfg, [[0, 0, 0], [2, 2, 2]])
    with torch.no_grad():
        m.grid.embeddings.uniform_(-0.1, 0.1)
    x = torch.rand(64, 3) * 2
    return m, x


def test_map_forward_matches_the_concatenated_decoders():
    m, x = _small_map()
    s, c = m(x)
    xn = m.normalize(x)
    b = m.blob(xn)
    h = m.sdf_net(torch.cat([m.grid(xn), b], -1))
    c2 = torch.sigmoid(m.color_net(torch.cat([b, h[:, 1:]], -1)))
    assert torch.allclose(s, h[:, 0], atol=1e-5) and torch.allclose(c, c2, atol=1e-5)
    assert c.min() >= 0 and c.max() <= 1 and m(x, color=False)[1] is None


def test_map_gradients_match_the_concatenated_decoders():
    """The split first layers (accumulated in place, ReLU in place) give the parameters and the
    points the gradients of the plain concatenated decoders."""
    m, x = _small_map()

    def grads(loss_fn, xx):
        m.zero_grad(set_to_none=True)
        loss_fn(xx).backward()
        return {k: p.grad.clone() for k, p in m.named_parameters()}

    def split(xx):
        s, c = m(xx)
        return (s * s).sum() + (c * c).sum()

    def concatenated(xx):
        xn = m.normalize(xx)
        b = m.blob(xn)
        h = m.sdf_net(torch.cat([m.grid(xn), b], -1))
        c = torch.sigmoid(m.color_net(torch.cat([b, h[:, 1:]], -1)))
        return (h[:, 0] ** 2).sum() + (c * c).sum()

    for needs_x in (False, True):
        xa, xb = x.clone().requires_grad_(needs_x), x.clone().requires_grad_(needs_x)
        ga, gb = grads(split, xa), grads(concatenated, xb)
        for k in ga:
            assert torch.allclose(ga[k], gb[k], atol=1e-6, rtol=1e-5), k
        if needs_x:
            assert torch.allclose(xa.grad, xb.grad, atol=1e-6, rtol=1e-5)


def test_smoothness_from_the_ray_query_matches_the_separate_grid_call():
    """Bundle adjustment takes the smoothness cube's features from the rays' grid call; loss and
    table gradient equal those of the separate smoothness_loss call."""
    from dynslam_cli.map.losses import smoothness_loss, smoothness_points, smoothness_tv
    from dynslam_cli.map.model import NeuralMap
    from dynslam_cli.map.render import render_rays

    torch.manual_seed(0)
    cfg = Config().map
    cfg.n_levels, cfg.log2_hashmap_size, cfg.SMOOTH_GRID, cfg.SMOOTH_VOXEL = 4, 10, 4, 0.2
    m = NeuralMap(cfg, [[-1, -1, 0], [1, 1, 3]])
    with torch.no_grad():
        m.grid.embeddings.uniform_(-0.1, 0.1)
    o = torch.zeros(1, 3)
    d = torch.nn.functional.normalize(torch.rand(32, 3) - torch.tensor([0.5, 0.5, -1.0]), dim=1)
    z = sample_depths(torch.full((32,), 1.5), cfg, torch.Generator().manual_seed(1))
    box = torch.tensor([[-1.0, -1.0, 0.0], [0.2, 0.2, 2.2]])
    grads, losses = [], []
    for merged in (False, True):
        m.zero_grad(set_to_none=True)
        g = torch.Generator().manual_seed(3)
        if merged:
            pts = smoothness_points(box, cfg, g)
            out = render_rays(m, o, d, z, grid_extra=pts)
            assert out["grid_extra"].shape == (4 ** 3, m.grid.out_dim)
            smooth = smoothness_tv(out["grid_extra"], cfg)
        else:
            out = render_rays(m, o, d, z)
            assert out["grid_extra"] is None
            smooth = smoothness_loss(m, box, cfg, g)
        loss = out["depth"].square().mean() + 1e3 * smooth
        loss.backward()
        losses.append(float(smooth.detach()))
        grads.append(m.grid.embeddings.grad.clone())
    assert losses[0] > 0 and abs(losses[0] - losses[1]) <= 1e-6 * losses[0]
    assert torch.allclose(grads[0], grads[1], rtol=1e-5, atol=1e-9)


class TestDropVertices:
    """map.mesh.drop_vertices: a mesh without some vertices, the faces using them and the vertices left bare."""

    @staticmethod
    def _quad():
        import trimesh

        v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 2, 2]], float)  # vertex 4 in no face
        f = np.array([[0, 1, 2], [0, 2, 3]])
        colors = np.array([[i * 10, 0, 0, 255] for i in range(5)], np.uint8)
        return trimesh.Trimesh(vertices=v, faces=f, vertex_colors=colors, process=False)

    def test_nothing_dropped_is_the_same_mesh(self):
        m = self._quad()
        assert drop_vertices(m, np.zeros(5, bool)) is m

    def test_one_vertex_takes_its_faces_and_the_bare_vertices(self):
        out = drop_vertices(self._quad(), np.array([False, False, False, True, False]))
        assert np.array_equal(out.vertices, [[0, 0, 0], [1, 0, 0], [1, 1, 0]])
        assert np.array_equal(out.faces, [[0, 1, 2]])
        assert np.array_equal(out.visual.vertex_colors[:, 0], [0, 10, 20])

    def test_every_face_dropped_leaves_an_empty_mesh(self):
        out = drop_vertices(self._quad(), np.array([True, False, False, False, False]))
        assert len(out.vertices) == 0 and len(out.faces) == 0
