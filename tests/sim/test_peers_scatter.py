"""bench/peers_scatter.py: the stand-in for torch-scatter's scatter_min that Taxim's torch backend imports."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

BENCH = Path(__file__).resolve().parents[2] / "bench" / "peers_scatter.py"


@pytest.fixture(scope="module")
def peers_scatter():
    spec = importlib.util.spec_from_file_location("peers_scatter", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def reference_min(src: np.ndarray, index: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Minimum along the last axis, one element at a time."""
    out = out.copy()
    for c in range(src.shape[0]):
        for i, j in enumerate(index):
            out[c, j] = min(out[c, j], src[c, i])
    return out


def test_scatter_min_into_out_as_taxim_calls_it(peers_scatter):
    """Taxim's call: src [C, N], a 1-D index [N], out [C, M] filled with inf; its values take part."""
    rng = np.random.default_rng(0)
    src = rng.normal(size=(3, 200)).astype(np.float32)
    index = rng.integers(0, 40, size=200)  # entries 40-49 receive nothing
    out = np.full((3, 50), np.inf, dtype=np.float32)
    out[:, :5] = -10.0  # existing values smaller than any src entry stay
    got = torch.from_numpy(out.copy())
    peers_scatter.scatter_min(torch.from_numpy(src), torch.from_numpy(index), dim_size=50, out=got)
    want = reference_min(src, index, out)
    np.testing.assert_array_equal(got.numpy(), want)
    assert (got[:, :5] == -10.0).all()
    assert np.isinf(got.numpy()[:, 40:]).all()


def test_scatter_min_new_out_is_zero_where_nothing_lands(peers_scatter):
    src = torch.tensor([[3.0, -1.0, 2.0]])
    out, arg = peers_scatter.scatter_min(src, torch.tensor([0, 0, 2]), dim_size=4)
    assert arg is None
    assert out.tolist() == [[-1.0, 0.0, 2.0, 0.0]]


def test_install_provides_the_module_only_when_missing(peers_scatter, monkeypatch):
    # None in sys.modules makes `import torch_scatter` fail as if it were not installed; monkeypatch puts
    # sys.modules back afterwards, so the stand-in does not outlive the test.
    monkeypatch.setitem(sys.modules, "torch_scatter", None)
    assert peers_scatter.install() == "scatter_reduce"
    import torch_scatter

    assert torch_scatter.scatter_min is peers_scatter.scatter_min
    assert peers_scatter.install() == "scatter_reduce"  # a second call still names the stand-in
