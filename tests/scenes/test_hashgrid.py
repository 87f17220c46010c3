"""The hash encoding's indexing and interpolation, and the hash-grid scene's early-terminating march."""

import pytest
import torch

from tnf.registry import from_dict
from tnf.scenes.hashgrid import PRIMES, HashEncoding, HashGridScene
from tnf.scenes.render import ray_box


def _encoding(**kw):
    torch.manual_seed(0)
    enc = HashEncoding(
        **{"levels": 3, "features": 2, "log2_table_size": 10, "base_resolution": 4, "max_resolution": 32, **kw}
    )
    with torch.no_grad():
        enc.table.normal_()
    return enc


def test_levels_grow_geometrically_and_coarse_levels_are_direct():
    enc = _encoding()
    assert enc.resolutions == [4, 11, 32]
    # (4+1)^3 = 125 and 12^3 = 1728 vs a 1024-entry table: only the first level fits.
    assert enc.n_dense == 1


def test_exact_at_grid_vertices():
    enc = _encoding()
    T = enc.table_size
    for level, res in enumerate(enc.resolutions):
        v = torch.tensor([[1, 2, 3], [res, 0, res - 1], [0, 0, 0]])
        x = v.float() / res
        out = enc(x).view(-1, enc.levels, enc.features)[:, level]
        if level < enc.n_dense:
            rows = v[:, 0] + v[:, 1] * (res + 1) + v[:, 2] * (res + 1) ** 2
        else:
            rows = (v[:, 0] * PRIMES[0]) ^ (v[:, 1] * PRIMES[1]) ^ (v[:, 2] * PRIMES[2])
            rows = rows % T
        expected = enc.table.detach()[level * T + rows]
        assert torch.allclose(out, expected, atol=1e-5), level


def test_direct_level_has_no_collisions():
    enc = _encoding()
    r = enc.resolutions[0]
    ar = torch.arange(r)
    cells = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), -1).reshape(-1, 1, 3).int()
    idx = enc.corner_index(cells.expand(-1, enc.levels, 3).contiguous())[:, 0].reshape(-1)
    assert idx.unique().numel() == (r + 1) ** 3


def test_trilinear_between_vertices_and_continuous():
    enc = _encoding(levels=1, max_resolution=4)
    # Halfway along an edge: the mean of its two end vertices.
    a, b = torch.tensor([[1 / 4, 2 / 4, 1 / 4]]), torch.tensor([[2 / 4, 2 / 4, 1 / 4]])
    mid = enc((a + b) / 2)
    assert torch.allclose(mid, (enc(a) + enc(b)) / 2, atol=1e-5)
    # Continuity across cell faces on every level.
    enc = _encoding()
    x = torch.rand(200, 3)
    eps = 1e-5
    assert (enc(x + eps) - enc(x)).abs().max() < 1e-2


def test_gradients_reach_only_the_looked_up_rows():
    enc = _encoding(levels=1, max_resolution=4)
    enc(torch.tensor([[0.1, 0.1, 0.1]])).sum().backward()
    assert (enc.table.grad.abs().sum(1) > 0).sum() == 8  # the 8 corners of one cell


@pytest.fixture
def scene():
    cfg = from_dict(
        HashGridScene.Config,
        {"bound": 0.1, "levels": 4, "log2_table_size": 12, "max_resolution": 64, "samples_per_ray": 96},
    )
    torch.manual_seed(0)
    s = HashGridScene(cfg)
    with torch.no_grad():
        s.encoding.table.normal_(0, 2)
        s.density_net[-1].bias[0] += 6.0  # dense enough that rays stop early
    return s


def test_march_matches_the_differentiable_pass(scene):
    o = torch.tensor([[0.0, 0.0, 0.3]]).repeat(300, 1)
    d = torch.nn.functional.normalize(torch.randn(300, 3) * 0.15 + torch.tensor([0, 0, -1.0]), dim=-1)
    dense = scene.render_rays(o, d)  # gradients enabled: every sample
    with torch.no_grad():
        marched = scene.render_rays(o, d)
    assert torch.isfinite(marched["t_stop"]).any()  # some rays did stop early
    # Every cell is occupied here, so the dense pass evaluates every sample inside the cube; the march
    # sends the network only those before each ray became opaque.
    near, far = ray_box(o, d, scene.bound)
    n = ((far - near) / scene.step_size - 0.5).ceil().clamp(0, scene.cfg.samples_per_ray)
    assert scene.march_stats["samples"] < 0.5 * float(n.sum())
    for k in ("rgb", "depth", "opacity"):
        assert torch.allclose(dense[k], marched[k], atol=1e-3), k


def test_occupancy_grid_skips_empty_space(scene):
    with torch.no_grad():
        scene.density_net[-1].bias[0] -= 30.0  # (nearly) empty everywhere
    scene.update_occupancy(step=10_000)
    assert scene.occupied.float().mean() < 1.0
    with torch.no_grad():
        out = scene.render_rays(torch.tensor([[0.0, 0.0, 0.3]]), torch.tensor([[0.0, 0.0, -1.0]]))
    assert float(out["opacity"][0]) < 1e-3 and torch.allclose(out["rgb"][0], scene.background)


def test_gather_rows_gradient_matches_index_select():
    import torch

    from tnf.scenes.hashgrid import gather_rows

    g = torch.Generator().manual_seed(0)
    table = torch.randn(50, 2, generator=g, requires_grad=True)
    idx = torch.randint(0, 50, (400,), generator=g)  # many repeated rows, as in the hash grid
    w = torch.randn(400, 2, generator=g)
    (gather_rows(table, idx) * w).sum().backward()
    ours = table.grad.clone()
    table.grad = None
    (table.index_select(0, idx) * w).sum().backward()
    assert torch.allclose(ours, table.grad, atol=1e-6)
    assert torch.equal(gather_rows(table, idx), table.index_select(0, idx))


def test_warp_kernel_equals_the_pytorch_encoding():
    from tnf.scenes import hash_kernel

    if not hash_kernel.available(torch.device("cpu")):
        pytest.skip("Warp does not run here")
    enc = _encoding(levels=4, max_resolution=64)  # one direct level, three hashed
    g = torch.Generator().manual_seed(1)
    x = torch.rand(500, 3, generator=g)
    x[:3] = torch.tensor([[1.0, 0.0, 1.0], [-0.2, 0.5, 1.3], [0.25, 0.5, 0.75]])  # faces, outside, vertices
    with torch.no_grad():
        ref = enc(x)
        out = hash_kernel.hash_encode(x, enc.table, enc.res, enc.n_dense, enc.table_size)
        half = hash_kernel.hash_encode(x, enc.table.half(), enc.res, enc.n_dense, enc.table_size)
    assert enc.n_dense == 1 and out.shape == ref.shape == (500, 8)
    assert torch.allclose(out, ref, atol=1e-5)
    assert torch.allclose(half, ref, atol=5e-3)  # float16 rows: 3 significant digits


@pytest.mark.parametrize("threads", [2, 3])
def test_warp_encoding_split_over_cpu_threads_is_the_one_launch(threads):
    """On the CPU the encoding runs as several launches on threads, each a block of samples: every feature is
    bit for bit the one launch's, whatever the blocks."""
    from tnf.scenes import hash_kernel

    if not hash_kernel.available(torch.device("cpu")):
        pytest.skip("Warp does not run here")
    enc = _encoding(levels=4, max_resolution=64)
    P = 3 * hash_kernel.CPU_SPLIT_MIN + 5  # blocks of unequal size
    x = torch.rand(P, 3, generator=torch.Generator().manual_seed(2))
    one = hash_kernel.hash_encode(x, enc.table, enc.res, enc.n_dense, enc.table_size, threads=1)
    split = hash_kernel.hash_encode(x, enc.table, enc.res, enc.n_dense, enc.table_size, threads=threads)
    assert split.shape == (P, 8) and torch.equal(split, one)
    with torch.no_grad():
        assert torch.allclose(one[-100:], enc(x[-100:]), atol=1e-5)  # the last block is encoded too


def test_trainable_warp_encoding_matches_the_pytorch_encoding_and_its_table_gradient():
    """``hash_encode_trainable`` (HashEncoding.train_kernel): the same features and the same gradient with respect
    to the table as the PyTorch encoding, with every sample's rows shifted by its own offset (batched objects)."""
    from tnf.scenes import hash_kernel

    if not hash_kernel.available(torch.device("cpu")):
        pytest.skip("Warp does not run here")
    enc = _encoding(levels=4, max_resolution=64)
    rows = enc.table.shape[0]
    with torch.no_grad():  # two objects' tables stacked, the second one different
        enc.table.data = torch.cat([enc.table, torch.randn_like(enc.table)])
    g = torch.Generator().manual_seed(3)
    x = torch.rand(400, 3, generator=g)
    x[:2] = torch.tensor([[1.0, 0.0, 1.0], [-0.2, 0.5, 1.3]])  # faces, outside
    offset = (torch.arange(400) % 2).to(torch.int32) * rows
    upstream = torch.randn(400, 8, generator=g)

    def features_and_grad(kernel: bool) -> tuple[torch.Tensor, torch.Tensor]:
        enc.table.grad = None
        enc.train_kernel = kernel
        out = enc(x, offset=offset)
        (out * upstream).sum().backward()
        return out.detach(), enc.table.grad.clone()

    ref, ref_grad = features_and_grad(False)
    out, grad = features_and_grad(True)
    assert torch.allclose(out, ref, atol=1e-5)
    assert torch.allclose(grad, ref_grad, atol=1e-5)
    assert grad[rows:].abs().sum() > 0 and grad[:rows].abs().sum() > 0  # both objects' rows were reached
    # Without offsets, only the first object's rows.
    enc.table.grad = None
    plain = enc(x)
    assert type(plain.grad_fn).__name__ == "_TrainableEncodingBackward"  # the kernels, not the PyTorch encoding
    (plain * upstream).sum().backward()
    assert enc.table.grad[rows:].abs().sum() == 0
    with pytest.raises(ValueError, match="no gradient with respect to the positions"):
        hash_kernel.hash_encode_trainable(x.requires_grad_(), enc.table, enc.res, enc.n_dense, enc.table_size)


def test_a_scene_renders_without_warp_through_the_pytorch_encoding(scene, monkeypatch):
    """Where Warp cannot be imported, rendering (render_kernel None) takes the PyTorch path, as where Warp has
    no device: the same images as that path asked for by name."""
    import sys

    import tnf.scenes

    o = torch.tensor([[0.0, 0.0, 0.3]]).repeat(50, 1)
    d = torch.nn.functional.normalize(torch.randn(50, 3) * 0.15 + torch.tensor([0, 0, -1.0]), dim=-1)
    monkeypatch.setattr(scene, "render_kernel", False)
    with torch.no_grad():
        plain = scene.render_rays(o, d)
    monkeypatch.setattr(scene, "render_kernel", None)
    monkeypatch.setitem(sys.modules, "warp", None)  # import warp raises ImportError
    monkeypatch.delitem(sys.modules, "tnf.scenes.hash_kernel", raising=False)
    monkeypatch.delattr(tnf.scenes, "hash_kernel", raising=False)
    assert not scene._use_kernel(torch.device("cpu"))
    with torch.no_grad():
        without = scene.render_rays(o, d)
    for k in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(without[k], plain[k], msg=k)
