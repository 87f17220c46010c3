"""The volume renderer against analytic cases, and the camera ray convention."""

import math

import torch

from tnf.cameras import camera_rays
from tnf.scenes.render import distortion_loss, interval_termination, ray_box, volume_render


def _uniform(R=4, N=100, length=1.0):
    edges = torch.linspace(0.0, length, N + 1).expand(R, N + 1)
    t = 0.5 * (edges[:, 1:] + edges[:, :-1])
    return t, edges[:, 1:] - edges[:, :-1]


def test_empty_space_is_transparent_and_shows_the_background():
    t, delta = _uniform()
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = volume_render(torch.zeros_like(t), torch.rand(*t.shape, 3), t, delta, bg)
    assert torch.allclose(out["opacity"], torch.zeros(4))
    assert torch.allclose(out["rgb"], bg.expand(4, 3))
    assert torch.equal(out["depth"], torch.zeros(4))


def test_opaque_slab_gives_its_depth_and_colour():
    t, delta = _uniform(N=200, length=2.0)
    sigma = torch.where((t > 1.25) & (t < 1.5), 1e4, 0.0)
    colour = torch.tensor([0.9, 0.1, 0.3])
    out = volume_render(sigma, colour.expand(*t.shape, 3), t, delta, torch.ones(3))
    assert torch.allclose(out["opacity"], torch.ones(4), atol=1e-6)
    assert torch.allclose(out["rgb"], colour.expand(4, 3), atol=1e-5)
    # The first sample inside the slab absorbs everything: its centre is within half a step of 1.25.
    assert torch.allclose(out["depth"], torch.full((4,), 1.25), atol=0.01)


def test_constant_medium_has_exponential_transmittance():
    length, sigma = 0.3, 4.0
    t, delta = _uniform(N=64, length=length)
    out = volume_render(torch.full_like(t, sigma), torch.ones(*t.shape, 3), t, delta, torch.zeros(3))
    expected = 1.0 - math.exp(-sigma * length)
    assert torch.allclose(out["opacity"], torch.full((4,), expected), atol=1e-5)
    # Black background, white medium: the colour is the opacity.
    assert torch.allclose(out["rgb"][:, 0], out["opacity"], atol=1e-6)
    # Expected depth of an exponential distribution truncated at L, normalised by opacity.
    mean_t = (1 / sigma - math.exp(-sigma * length) * (length + 1 / sigma)) / expected
    assert abs(float(out["depth"][0]) - mean_t) < 1e-3


def test_camera_rays_follow_the_opengl_convention():
    c2w = torch.eye(4)[None].clone()
    c2w[0, :3, 3] = torch.tensor([0.0, 0.0, 2.0])
    o, d, z = camera_rays(c2w, torch.tensor([10.0, 10.0, 2.0, 2.0]), 4, 4)
    assert o.shape == d.shape == (1, 4, 4, 3) and z.shape == (1, 4, 4)
    assert torch.allclose(d.norm(dim=-1), torch.ones(1, 4, 4))
    # Pixel (row 0, col 0) lies up-left of the centre: x < 0, y > 0 in the camera, looking along -z.
    assert d[0, 0, 0, 0] < 0 and d[0, 0, 0, 1] > 0 and (d[..., 2] < 0).all()
    # Symmetric pixels about the principal point (2, 2): rows 1 and 2 have opposite y.
    assert torch.allclose(d[0, 1, 1, 1], -d[0, 2, 2, 1])
    assert torch.allclose(z, -d[..., 2])


def test_ray_box_entry_and_exit():
    o = torch.tensor([[0.0, 0.0, 2.0], [5.0, 5.0, 2.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    near, far = ray_box(o, d, 0.5)
    assert torch.allclose(near[0], torch.tensor(1.5)) and torch.allclose(far[0], torch.tensor(2.5))
    assert far[1] <= near[1]  # a miss


def test_interval_starts_put_an_opaque_surface_where_it_begins():
    # Coarse samples (step 0.1) and a surface at 1.23, between two samples: each interval is
    # [t - delta/2, t + delta/2). Without starts the depth is the first inside sample's centre (1.25 or
    # deeper); with them, an opaque interval ends light where it begins.
    t, delta = _uniform(N=20, length=2.0)
    start = t - 0.5 * delta
    sigma = torch.where(start >= 1.2 - 1e-6, 1e5, 0.0)
    out = volume_render(sigma, torch.ones(*t.shape, 3), t, delta, torch.zeros(3), start=start)
    assert torch.allclose(out["depth"], torch.full((4,), 1.2), atol=1e-4)
    plain = volume_render(sigma, torch.ones(*t.shape, 3), t, delta, torch.zeros(3))
    assert torch.allclose(plain["depth"], torch.full((4,), 1.25), atol=1e-4)


def test_interval_starts_give_the_exact_depth_of_a_constant_medium():
    # Few coarse intervals: the per-interval exact termination point makes the quadrature's depth equal the
    # closed form, where placing each interval's share at its centre does not.
    length, sigma = 0.3, 20.0
    t, delta = _uniform(N=6, length=length)
    out = volume_render(
        torch.full_like(t, sigma), torch.ones(*t.shape, 3), t, delta, torch.zeros(3), start=t - 0.5 * delta
    )
    expected = 1.0 - math.exp(-sigma * length)
    mean_t = (1 / sigma - math.exp(-sigma * length) * (length + 1 / sigma)) / expected
    assert abs(float(out["depth"][0]) - mean_t) < 1e-5


def test_interval_termination_limits():
    tau = torch.tensor([0.0, 1e-4, 1.0, 50.0])
    f = interval_termination(tau)
    assert abs(float(f[0]) - 0.5) < 1e-6 and abs(float(f[1]) - 0.5) < 1e-4
    assert abs(float(f[2]) - (1.0 - 1.0 / (math.e - 1.0))) < 1e-6
    assert float(f[3]) < 0.021  # opaque: light ends near where the interval begins


def test_distortion_loss_is_small_for_a_surface_and_large_for_a_spread():
    t, delta = _uniform(R=1, N=50, length=1.0)
    peaked = torch.zeros_like(t)
    peaked[0, 25] = 1.0
    spread = torch.full_like(t, 1.0 / 50)
    lp, ls = distortion_loss(peaked, t, delta), distortion_loss(spread, t, delta)
    # One sample: only the self term w^2 delta / 3. Uniform over [0, 1]: E|t_i - t_j| = 1/3.
    assert torch.allclose(lp, torch.tensor([delta[0, 25] / 3.0]))
    assert abs(float(ls[0]) - 1.0 / 3.0) < 0.01
    # The O(N) form equals the double sum.
    w = torch.rand(2, 30)
    tt, dd = _uniform(R=2, N=30, length=1.0)
    brute = (w[:, :, None] * w[:, None, :] * (tt[:, :, None] - tt[:, None, :]).abs()).sum((1, 2))
    brute = brute + (w**2 * dd).sum(-1) / 3.0
    assert torch.allclose(distortion_loss(w, tt, dd), brute, atol=1e-6)
