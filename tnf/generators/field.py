"""A learned feature field over the surfaces of the objects a generator was trained on.

The scenes fitted to a few dozen photographs hold an object's shape to about a millimetre; the relief a gel
shows (knurling, pitted peel, a raised panel's edge) is finer, and what an RGB-D crop does not hold a generator
cannot draw from it. Yet every training touch of an object saw part of that relief, at a known place on the
object. ``SurfaceField`` stores what the training touches teach about each place: a multi-resolution hash grid
(as Instant-NGP's) over the object's own frame, salted by the object, looked up at the surface point each
RGB-D pixel sees (``tnf.data.render.crop_points``) and learned with the generator, end to end. A new touch of a
trained object finds there what earlier touches of the same place taught; an object the field never saw gets
zeros, so the generator falls back on the RGB-D crop (it is trained that way too, ``dropout``).

What it does for sim_digit (docs/decisions/generator_prior_surface.md, "The surface"):
touches of places the training touches pressed gain most where the relief is finest (validation SSIM
0.9772 against 0.9758 over three seeds; the flashlight's knurled grip 0.941 to 0.969); touches of places no
training touch reached read features the field was not taught there (the table is shared and hashed) and score
lower (novel views 0.968 against 0.974).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from tnf.errors import TnfError
from tnf.scenes.hashgrid import PRIMES, gather_rows

OBJECT_PRIME = 3_674_653_429
"""Hash multiplier of the object, a fourth axis beside the scenes' spatial hash (``PRIMES`` for x, y and z)."""


class SurfaceField(nn.Module):
    """Features of points on trained objects' surfaces: ``field(points, object_id) -> [B, levels * features, H, W]``.

    Args:
        levels: grid resolutions, from ``coarsest`` to ``finest`` cell size in geometric steps.
        features: features stored per grid vertex and level.
        coarsest: the coarsest cell size in metres.
        finest: the finest cell size in metres.
        log2_table: hash table entries per level, as a power of two (shared by all objects).
        max_objects: object ids the field can record as seen (``object_id`` must be below it).
        dropout: while training, the share of pairs whose features are zeroed, so that the generator also learns
            to work without them (objects the field never saw).

    Features start near zero (within 1e-4), so a new field adds almost nothing until training writes into it.
    Each pixel's feature is the trilinear interpolation of its cell's eight vertices, level by level. Pixels whose
    point is NaN (no surface), pairs with ``object_id < 0`` and, outside training, objects never seen in training
    get zeros.
    """

    def __init__(
        self,
        levels: int = 5,
        features: int = 2,
        coarsest: float = 0.008,
        finest: float = 0.0005,
        log2_table: int = 20,
        max_objects: int = 1024,
        dropout: float = 0.25,
    ):
        super().__init__()
        if levels < 1 or features < 1:
            raise TnfError(f"a surface field needs levels >= 1 and features >= 1, got {levels} and {features}")
        if not 0 < finest <= coarsest:
            raise TnfError(f"surface field cell sizes must satisfy 0 < finest <= coarsest, got {finest}, {coarsest}")
        if not 4 <= log2_table <= 26:
            raise TnfError(f"surface field log2_table must be in [4, 26], got {log2_table}")
        if not 0 <= dropout < 1:
            raise TnfError(f"surface field dropout must be in [0, 1), got {dropout}")
        self.levels, self.features, self.dropout = levels, features, dropout
        # Small random features (as Instant-NGP): all zeros would reach the generator's ReLUs at exactly 0, where
        # no gradient passes, and the field would never learn.
        self.table = nn.Parameter(torch.empty(levels, 2**log2_table, features).uniform_(-1e-4, 1e-4))
        growth = (coarsest / finest) ** (1 / max(levels - 1, 1))
        self.cell: torch.Tensor
        self.register_buffer("cell", torch.tensor([coarsest / growth**i for i in range(levels)]), persistent=False)
        self.seen: torch.Tensor
        self.register_buffer("seen", torch.zeros(max_objects, dtype=torch.bool))

    @property
    def channels(self) -> int:
        return self.levels * self.features

    def forward(self, points: torch.Tensor, object_id: torch.Tensor) -> torch.Tensor:
        """``points`` [B, 3, H, W] in metres (NaN: no surface), ``object_id`` [B] long -> [B, C, H, W] float32."""
        if points.dim() != 4 or points.shape[1] != 3:
            raise TnfError(f"surface points must be [B, 3, H, W], got {tuple(points.shape)}")
        b, _, h, w = points.shape
        if object_id.shape != (b,):
            raise TnfError(f"object_id must be [{b}], one per pair, got {tuple(object_id.shape)}")
        if b and int(object_id.max()) >= len(self.seen):
            raise TnfError(f"object id {int(object_id.max())} is beyond the field's {len(self.seen)} objects")
        obj = object_id.to(points.device).long()
        known = obj >= 0
        if self.training:
            self.seen[obj[known]] = True
            if self.dropout > 0:
                known = known & (torch.rand(b, device=obj.device) >= self.dropout)
        else:
            known = known & self.seen[obj.clamp_min(0)]
        x = points.float().permute(0, 2, 3, 1).reshape(-1, 3)
        valid = torch.isfinite(x).all(1) & known.repeat_interleave(h * w)
        x = torch.where(valid[:, None], x, torch.zeros_like(x))
        salt = obj.clamp_min(0).repeat_interleave(h * w) * OBJECT_PRIME
        mask = self.table.shape[1] - 1
        out = []
        for level in range(self.levels):
            p = x / self.cell[level]
            p0 = torch.floor(p)
            frac = p - p0
            i0 = p0.long()
            # Per axis, the hash term and the interpolation weight of the cell's lower (0) and upper (1) vertex.
            hx, hy, hz = ([i0[:, a] * PRIMES[a], (i0[:, a] + 1) * PRIMES[a]] for a in range(3))
            wx, wy, wz = ([1 - frac[:, a], frac[:, a]] for a in range(3))
            acc = x.new_zeros(len(x), self.features)
            for cx in (0, 1):  # the eight vertices one at a time: no [N, 8, 3] index tensor in memory
                for cy in (0, 1):
                    for cz in (0, 1):
                        index = (hx[cx] ^ hy[cy] ^ hz[cz] ^ salt) & mask
                        # The scenes' gather: its gradient is an index_add (on a GPU; a bincount on a CPU), where
                        # indexing's sorts the indices first, far slower for a batch's million points.
                        rows = gather_rows(self.table[level], index)
                        acc = acc + rows * (wx[cx] * wy[cy] * wz[cz])[:, None]
            out.append(acc)
        feats = torch.cat(out, 1) * valid[:, None]
        return feats.reshape(b, h, w, -1).permute(0, 3, 1, 2)

    def extra_repr(self) -> str:
        cells = ", ".join(f"{1000 * float(c):.2g}" for c in self.cell)
        return (
            f"levels={self.levels}, features={self.features}, cells_mm=[{cells}], "
            f"table=2^{int(math.log2(self.table.shape[1]))}, dropout={self.dropout}"
        )
