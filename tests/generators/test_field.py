"""The surface field (``tnf.generators.field``): a hash grid over trained objects' surfaces, learned end to end."""

from __future__ import annotations

import math

import pytest
import torch

from tnf.errors import TnfError
from tnf.generators.field import SurfaceField


def _points(n: int, seed: int) -> torch.Tensor:
    """[n, 3, 4, 4] points on a 3 cm patch of the plane z = 0.01."""
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, 4, 4, generator=g) * 0.03
    return torch.cat([xy, torch.full((n, 1, 4, 4), 0.01)], 1)


def test_a_new_field_adds_almost_nothing_and_unknown_places_get_zeros():
    f = SurfaceField(levels=3, features=2, log2_table=10, dropout=0.0)
    pts = _points(2, 0)
    assert f.channels == 6 and f(pts, torch.tensor([0, 1])).abs().max() <= 1e-4
    with torch.no_grad():
        f.table.normal_()
    f.train()
    f(pts, torch.tensor([0, 1]))  # training marks objects 0 and 1 as seen
    f.eval()
    pts[0, :, 0, 0] = math.nan  # no surface under this pixel
    out = f(pts, torch.tensor([0, 3]))
    assert torch.equal(out[0, :, 0, 0], torch.zeros(6)) and out[0, :, 1:].abs().sum() > 0
    assert torch.equal(out[1], torch.zeros(6, 4, 4))  # object 3 was never trained: the generator sees no field
    assert torch.equal(f(pts, torch.tensor([-1, 0]))[0], torch.zeros(6, 4, 4))  # -1: an object outside the vocabulary
    # The same place of the same object gives the same features, another object's the same place others.
    again = f(pts.flip(0), torch.tensor([3, 0]))
    assert torch.allclose(again[1], out[0]) and not torch.allclose(f(pts, torch.tensor([1, 1]))[0], out[0])


def test_features_are_continuous_in_the_point():
    f = SurfaceField(levels=4, features=2, log2_table=12, dropout=0.0)
    with torch.no_grad():
        f.table.normal_()
    f.train()
    pts = _points(1, 1)
    near = pts + 1e-7  # far below the finest cell (0.5 mm): trilinear interpolation moves the features little
    a, b = f(pts, torch.tensor([0])), f(near, torch.tensor([0]))
    assert (a - b).abs().max() < 1e-2 and a.abs().max() > 0.1


def test_training_dropout_zeroes_whole_pairs():
    f = SurfaceField(levels=2, features=1, log2_table=8, dropout=0.5)
    with torch.no_grad():
        f.table.fill_(1.0)
    f.train()
    torch.manual_seed(0)
    out = f(_points(64, 2), torch.zeros(64, dtype=torch.long))
    per_pair = out.flatten(1).abs().sum(1)
    dropped = per_pair == 0
    assert 16 < int(dropped.sum()) < 48 and bool((per_pair[~dropped] > 0).all())


def test_the_field_learns_each_objects_pattern_and_recalls_it_at_new_points():
    # Two objects share the same coordinates but carry opposite millimetre-scale ridges: a position-only model
    # cannot tell them apart, the field (salted by object) can, and recalls the pattern at points it never saw.
    torch.manual_seed(0)
    f = SurfaceField(levels=4, features=2, coarsest=0.008, finest=0.0005, log2_table=14, dropout=0.0)
    readout = torch.nn.Linear(f.channels, 1)
    opt = torch.optim.Adam([{"params": f.parameters(), "lr": 0.02}, {"params": readout.parameters(), "lr": 0.01}])

    def target(pts: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        sign = 1 - 2 * obj.float().view(-1, 1, 1)
        return sign * torch.sin(2 * math.pi * pts[:, 0] / 0.004)  # 4 mm ridges along x

    def predict(pts: torch.Tensor, obj: torch.Tensor) -> torch.Tensor:
        return readout(f(pts, obj).permute(0, 2, 3, 1))[..., 0]

    f.train()
    for step in range(300):
        pts, obj = _points(32, 100 + step), torch.randint(0, 2, (32,))
        loss = (predict(pts, obj) - target(pts, obj)).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    f.eval()
    pts, obj = _points(64, 7), torch.arange(64) % 2
    with torch.no_grad():
        err = (predict(pts, obj) - target(pts, obj)).pow(2).mean()
    assert err < 0.1 * target(pts, obj).pow(2).mean()  # the ridges' variance is 0.5


def test_bad_settings_and_inputs_are_clear_errors():
    with pytest.raises(TnfError, match="finest <= coarsest"):
        SurfaceField(coarsest=0.001, finest=0.002)
    with pytest.raises(TnfError, match="log2_table"):
        SurfaceField(log2_table=40)
    f = SurfaceField(levels=2, features=1, log2_table=8, max_objects=4)
    with pytest.raises(TnfError, match=r"\[B, 3, H, W\]"):
        f(torch.zeros(2, 4, 4, 3), torch.zeros(2, dtype=torch.long))
    with pytest.raises(TnfError, match="beyond the field's 4 objects"):
        f(_points(1, 0), torch.tensor([4]))
