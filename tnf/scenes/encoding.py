"""The hash-grid scene's networks: the multiresolution hash encoding (Instant-NGP), the spherical-harmonics
encoding of view directions and the small MLPs, in pure PyTorch.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

# Instant-NGP's spatial hash primes (the first is 1 so that x varies fastest, for cache coherence).
PRIMES = (1, 2654435761, 805459861)


class HashEncoding(nn.Module):
    """Multiresolution hash encoding: L levels of F features each, trilinearly interpolated.

    Level l has resolution ``N_l = floor(base * b**l)`` cells per axis with b chosen so that the last
    level has ``max_resolution``. A level whose ``(N_l + 1)**3`` vertices fit in the table is indexed
    directly (no collisions); finer levels use the spatial hash ``(x * 1) ^ (y * p1) ^ (z * p2) mod T``.

    Input: [P, 3] positions in [0, 1]^3. Output: [P, L * F].
    """

    #: Training's encoding and table gradient by Warp kernels (``hash_kernel.hash_encode_trainable``), in
    #: place of the [P, L, 8] tensors below; a fit sets it from ``fit.train_kernel``.
    train_kernel: bool = False

    # Buffers registered in ``__init__`` (declared here for type checkers).
    res: torch.Tensor
    stride: torch.Tensor
    primes: torch.Tensor
    level_offset: torch.Tensor

    def __init__(
        self,
        levels: int = 16,
        features: int = 2,
        log2_table_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 2048,
    ):
        super().__init__()
        self.levels, self.features = levels, features
        self.table_size = T = 1 << log2_table_size
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(levels - 1, 1))
        res = [int(math.floor(base_resolution * growth**lvl)) for lvl in range(levels)]
        self.resolutions = res
        dense = [(r + 1) ** 3 <= T for r in res]
        self.register_buffer("res", torch.tensor(res, dtype=torch.float32), persistent=False)
        # Direct indexing strides (1, N+1, (N+1)^2) for dense levels; hash primes for the others.
        # Coarse levels are indexed directly; they come first since resolution grows with the level.
        self.n_dense = sum(dense)
        self.register_buffer(
            "stride", torch.tensor([[1, r + 1, (r + 1) ** 2] for r in res], dtype=torch.int32), persistent=False
        )
        primes32 = [p - (1 << 32) if p >= (1 << 31) else p for p in PRIMES]  # same low bits as the primes
        self.register_buffer("primes", torch.tensor(primes32, dtype=torch.int32), persistent=False)
        self.register_buffer("level_offset", torch.arange(levels, dtype=torch.int32) * T, persistent=False)
        # One table of L * T rows; small uniform init as in Instant-NGP.
        self.table = nn.Parameter(torch.empty(levels * T, features).uniform_(-1e-4, 1e-4))

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def corner_index(self, base: torch.Tensor) -> torch.Tensor:
        """Table rows of the 8 corners of the cells whose lowest corners are ``base`` [P, L, 3] -> [P, L, 2, 2, 2].

        Corner (i, j, k) is ``base + (i, j, k)``. Arithmetic is in int32: the hash only keeps the low bits,
        which wrap-around multiplication leaves intact, and direct indices are below the table size.
        """
        nd = self.n_dense
        parts = []
        for sl, mult, combine in ((slice(0, nd), self.stride, "add"), (slice(nd, None), self.primes, "xor")):
            b = base[:, sl]
            if b.shape[1] == 0:
                continue
            m = mult[sl] if mult.dim() == 2 else mult
            # Per axis, the two coordinates (lower, upper) times the axis multiplier, broadcast to 2x2x2.
            c = [torch.stack([b[..., a] * m[..., a], (b[..., a] + 1) * m[..., a]], dim=-1) for a in range(3)]
            c0, c1, c2 = c[0][..., :, None, None], c[1][..., None, :, None], c[2][..., None, None, :]
            if combine == "add":
                parts.append(c0 + c1 + c2)
            else:
                parts.append((c0 ^ c1 ^ c2) & (self.table_size - 1))
        idx = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]
        return idx + self.level_offset.view(1, -1, 1, 1, 1)

    def forward(
        self, x: torch.Tensor, table: torch.Tensor | None = None, offset: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Features [P, L * F] at positions x [P, 3] in [0, 1]^3.

        ``table``: rows read instead of the trainable table, without gradients (rendering passes a
        half-precision copy); the output has its dtype. Cell coordinates stay float32 either way: the
        finest levels need more bits than half precision has. ``offset``: [P] integer rows added to every
        row sample p reads (``tnf.scenes.batched``: where its object's levels start in a table that stacks
        several objects' tables).
        """
        if table is None and self.train_kernel:
            from tnf.scenes.hash_kernel import hash_encode_trainable  # lazy: imports warp

            return hash_encode_trainable(x, self.table, self.res, self.n_dense, self.table_size, offset)
        P = x.shape[0]
        scaled = x.clamp(0.0, 1.0).unsqueeze(1) * self.res.view(1, -1, 1)  # [P, L, 3]
        base = scaled.floor()
        # The top face of the cube (x == 1) belongs to the last cell, not to a cell outside the grid.
        base = torch.minimum(base, self.res.view(1, -1, 1) - 1).to(torch.int32)
        frac = scaled - base
        idx = self.corner_index(base)  # [P, L, 2, 2, 2]
        if offset is not None:
            idx = idx + offset.to(torch.int64 if self.table.shape[0] > 2**31 - 1 else idx.dtype).view(-1, 1, 1, 1, 1)
        # Trilinear weights, broadcast the same way as the corners.
        w = [torch.stack([1.0 - frac[..., a], frac[..., a]], dim=-1) for a in range(3)]
        weights = w[0][..., :, None, None] * w[1][..., None, :, None] * w[2][..., None, None, :]
        if table is None:
            feats = gather_rows(self.table, idx.reshape(-1))
        else:
            feats, weights = table.index_select(0, idx.reshape(-1)), weights.to(table.dtype)
        feats = feats.view(P, self.levels, 8, self.features)
        out = (feats * weights.reshape(P, self.levels, 8, 1)).sum(2)
        return out.reshape(P, -1)


class _GatherRows(torch.autograd.Function):
    """``table[idx]`` whose backward accumulates with ``bincount`` on the CPU (several times faster there
    than ``index_add_``, which the hash grid's millions of repeated rows make the slowest op of a step)."""

    @staticmethod
    def forward(ctx: Any, table: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(idx)
        ctx.rows = table.shape[0]
        return table.index_select(0, idx)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        (idx,) = ctx.saved_tensors
        if grad.is_cuda:
            out = grad.new_zeros(ctx.rows, grad.shape[1]).index_add_(0, idx, grad)
        else:
            cols = [torch.bincount(idx, weights=grad[:, f], minlength=ctx.rows) for f in range(grad.shape[1])]
            out = torch.stack(cols, dim=1).to(grad.dtype)
        return out, None


def gather_rows(table: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows ``table[idx]`` ([len(idx), F]), differentiable with respect to ``table``."""
    return _GatherRows.apply(table, idx)


def spherical_harmonics(d: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics up to degree 4 (16 values) of unit directions [P, 3] -> [P, 16]."""
    x, y, z = d.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    return torch.stack(
        [
            torch.full_like(x, 0.28209479177387814),
            -0.48860251190291987 * y,
            0.48860251190291987 * z,
            -0.48860251190291987 * x,
            1.0925484305920792 * xy,
            -1.0925484305920792 * yz,
            0.94617469575755997 * zz - 0.31539156525251999,
            -1.0925484305920792 * xz,
            0.54627421529603959 * (xx - yy),
            0.59004358992664352 * y * (-3.0 * xx + yy),
            2.8906114426405538 * xy * z,
            0.45704579946446572 * y * (1.0 - 5.0 * zz),
            0.3731763325901154 * z * (5.0 * zz - 3.0),
            0.45704579946446572 * x * (1.0 - 5.0 * zz),
            1.4453057213202769 * z * (xx - yy),
            0.59004358992664352 * x * (-xx + 3.0 * yy),
        ],
        dim=-1,
    )


def mlp(inp: int, hidden: int, out: int, layers: int) -> nn.Sequential:
    """``layers`` hidden layers of width ``hidden`` with ReLU, then a linear output layer."""
    mods: list[nn.Module] = []
    d = inp
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    mods.append(nn.Linear(d, out))
    return nn.Sequential(*mods)
