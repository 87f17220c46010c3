"""``hashgrid``: a multiresolution hash encoding (Instant-NGP) with small MLPs, in pure PyTorch.

The object sits in the cube [-bound, bound]^3 around the origin. Rays are marched with a fixed step
(``samples_per_ray`` steps across the cube's diagonal); an occupancy grid, refreshed during training from
the field's own density, removes samples in empty space before the network sees them, so only the few
samples near the surface cost a hash-grid lookup.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from tnf.registry import SCENES
from tnf.scenes.render import EMPTY_OPACITY, FieldScene, RayOutput, ray_box, volume_render

# Instant-NGP's spatial hash primes (the first is 1 so that x varies fastest, for cache coherence).
PRIMES = (1, 2654435761, 805459861)


class HashEncoding(nn.Module):
    """Multiresolution hash encoding: L levels of F features each, trilinearly interpolated.

    Level l has resolution ``N_l = floor(base * b**l)`` cells per axis with b chosen so that the last
    level has ``max_resolution``. A level whose ``(N_l + 1)**3`` vertices fit in the table is indexed
    directly (no collisions); finer levels use the spatial hash ``(x * 1) ^ (y * p1) ^ (z * p2) mod T``.

    Input: [P, 3] positions in [0, 1]^3. Output: [P, L * F].
    """

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

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        P = x.shape[0]
        scaled = x.clamp(0.0, 1.0).unsqueeze(1) * self.res.view(1, -1, 1)  # [P, L, 3]
        base = scaled.floor()
        # The top face of the cube (x == 1) belongs to the last cell, not to a cell outside the grid.
        base = torch.minimum(base, self.res.view(1, -1, 1) - 1).to(torch.int32)
        frac = scaled - base
        idx = self.corner_index(base)  # [P, L, 2, 2, 2]
        # Trilinear weights, broadcast the same way as the corners.
        w = [torch.stack([1.0 - frac[..., a], frac[..., a]], dim=-1) for a in range(3)]
        weights = w[0][..., :, None, None] * w[1][..., None, :, None] * w[2][..., None, None, :]
        feats = gather_rows(self.table, idx.reshape(-1)).view(P, self.levels, 8, self.features)
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


@SCENES.register("hashgrid")
class HashGridScene(FieldScene):
    """Instant-NGP style hash-grid radiance field with an occupancy grid (pure PyTorch, CPU or CUDA)."""

    # Buffers registered in ``__init__`` (declared here for type checkers).
    occ_density: torch.Tensor
    occupied: torch.Tensor
    hull: torch.Tensor

    @dataclass
    class Config:
        levels: int = 16
        """Number of hash-grid levels."""
        features_per_level: int = 2
        """Features stored per grid vertex and level."""
        log2_table_size: int = 19
        """log2 of the entries per level's hash table (19 -> 524288)."""
        base_resolution: int = 16
        """Cells per axis of the coarsest level."""
        max_resolution: int = 2048
        """Cells per axis of the finest level."""
        hidden: int = 64
        """Width of the density and colour MLPs."""
        geo_features: int = 15
        """Features the density MLP passes to the colour MLP."""
        density_layers: int = 1
        """Hidden layers of the density MLP."""
        color_layers: int = 2
        """Hidden layers of the colour MLP."""
        samples_per_ray: int = 512
        """Ray-marching steps across the cube's diagonal (step = 2 sqrt(3) bound / samples_per_ray)."""
        occupancy_resolution: int = 64
        """Cells per axis of the occupancy grid."""
        occupancy_threshold: float = 0.01
        """A cell is empty when a step through it would absorb less than this fraction of light."""
        occupancy_update_every: int = 16
        """Training steps between occupancy-grid refreshes."""
        occupancy_warmup: int = 256
        """Training steps before empty cells start being skipped."""
        occupancy_decay: float = 0.95
        """Decay of the grid's running density at each refresh (forgets floaters that training removes)."""
        bound: float | None = None
        """Half-size of the cube [-bound, bound]^3 around the origin that holds the object, metres;
        null: derived from the training cameras when fitting."""
        background: tuple[float, float, float] = (1.0, 1.0, 1.0)
        """RGB colour in [0, 1] behind the object."""

        def validate(self) -> None:
            if self.levels < 1 or self.features_per_level < 1:
                raise ValueError(f"levels and features_per_level must be >= 1, got {self.levels}")
            if not 8 <= self.log2_table_size <= 26:
                raise ValueError(f"log2_table_size must be in 8..26, got {self.log2_table_size}")
            if not 1 <= self.base_resolution <= self.max_resolution:
                raise ValueError(
                    f"need 1 <= base_resolution <= max_resolution, got {self.base_resolution}, {self.max_resolution}"
                )
            if self.samples_per_ray < 8 or self.occupancy_resolution < 4:
                raise ValueError("samples_per_ray must be >= 8 and occupancy_resolution >= 4")
            if self.bound is not None and self.bound <= 0:
                raise ValueError(f"bound must be > 0 metres, got {self.bound}")

    def __init__(self, cfg: Config):
        if cfg.bound is None:
            raise ValueError("hashgrid scene needs a bound; fitting derives it from the cameras")
        super().__init__(cfg.bound, cfg.background)
        self.cfg = cfg
        self.encoding = HashEncoding(
            cfg.levels, cfg.features_per_level, cfg.log2_table_size, cfg.base_resolution, cfg.max_resolution
        )
        self.density_net = mlp(self.encoding.out_dim, cfg.hidden, 1 + cfg.geo_features, cfg.density_layers)
        self.color_net = mlp(16 + cfg.geo_features, cfg.hidden, 3, cfg.color_layers)
        G = cfg.occupancy_resolution
        self.step_size = 2.0 * math.sqrt(3.0) * self.bound / cfg.samples_per_ray
        self.register_buffer("occ_density", torch.zeros(G**3))
        self.register_buffer("occupied", torch.ones(G**3, dtype=torch.bool))
        # Cells inside the visual hull of the training masks (all, until ``carve`` is called).
        self.register_buffer("hull", torch.ones(G**3, dtype=torch.bool))

    # -- field --------------------------------------------------------------------------------------
    def _normalise(self, pos: torch.Tensor) -> torch.Tensor:
        return (pos + self.bound) / (2.0 * self.bound)

    def density(self, pos: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density [P] (1/metre) and geometry features [P, geo] at world positions [P, 3] (metres)."""
        h = self.density_net(self.encoding(self._normalise(pos)))
        # exp activation (clamped against overflow) as in Instant-NGP; biased down so space starts thin.
        sigma = torch.exp((h[:, 0] - 1.0).clamp(max=15.0))
        return sigma, h[:, 1:]

    def field(self, pos: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Density [P] and colour [P, 3] in [0, 1] at positions [P, 3] seen along unit dirs [P, 3]."""
        sigma, geo = self.density(pos)
        rgb = torch.sigmoid(self.color_net(torch.cat([spherical_harmonics(dirs), geo], dim=-1)))
        return sigma, rgb

    # -- occupancy grid -----------------------------------------------------------------------------
    def _cell_index(self, pos: torch.Tensor) -> torch.Tensor:
        G = self.cfg.occupancy_resolution
        c = (self._normalise(pos) * G).long().clamp(0, G - 1)
        return (c[..., 0] * G + c[..., 1]) * G + c[..., 2]

    @torch.no_grad()
    def update_occupancy(self, step: int) -> None:
        """Refresh the occupancy grid every ``occupancy_update_every`` steps from the field's density."""
        cfg = self.cfg
        if step % cfg.occupancy_update_every != 0:
            return
        G = cfg.occupancy_resolution
        dev = self.occ_density.device
        ar = torch.arange(G, device=dev)
        cells = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), dim=-1).reshape(-1, 3).float()
        # Only cells inside the visual hull can ever be occupied; the rest keep zero density.
        inside = self.hull.nonzero(as_tuple=True)[0]
        sigma = torch.zeros(G**3, device=dev)
        chunk = 1 << 18
        for i in range(0, inside.numel(), chunk):
            sel = inside[i : i + chunk]
            c = cells[sel]
            # A random point in each cell, so thin structures between cell centres are found over time.
            pos = ((c + torch.rand_like(c)) / G) * (2 * self.bound) - self.bound
            sigma[sel] = self.density(pos)[0]
        self.occ_density.copy_(torch.maximum(self.occ_density * cfg.occupancy_decay, sigma))
        if step < cfg.occupancy_warmup:
            self.occupied.copy_(self.hull)
            return
        threshold = -math.log(1.0 - cfg.occupancy_threshold) / self.step_size
        threshold = min(threshold, float(self.occ_density[self.hull].mean()) if self.hull.any() else 0.0)
        self.occupied.copy_((self.occ_density > threshold) & self.hull)

    @torch.no_grad()
    def carve(self, c2w: torch.Tensor, intrinsics: torch.Tensor, alpha: torch.Tensor) -> float:
        """Restrict the occupancy grid to the visual hull of the training views' masks (space carving).

        A cell stays when, in every view that sees it, its projection touches the (dilated) object mask, so
        the field never spends samples where all cameras saw background. ``c2w`` [N, 4, 4] (OpenGL),
        ``intrinsics`` [N, 4] (fx, fy, cx, cy) pixels, ``alpha`` [N, H, W] in [0, 1]. Returns the fraction
        of cells kept. Views whose alpha is everywhere opaque (no mask) carve nothing.
        """
        from scipy.ndimage import distance_transform_edt

        G = self.cfg.occupancy_resolution
        dev = self.hull.device
        ar = torch.arange(G, device=dev, dtype=torch.float32)
        cells = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), dim=-1).reshape(-1, 3)
        centres = (cells + 0.5) / G * (2 * self.bound) - self.bound  # [G^3, 3] metres
        radius = math.sqrt(3.0) * self.bound / G  # half-diagonal of a cell, metres
        keep = torch.ones(G**3, dtype=torch.bool, device=dev)
        N, H, W = alpha.shape
        for k in range(N):
            mask = alpha[k].to(dev) > 0.5
            if bool(mask.all()) or not bool(mask.any()):
                continue  # no mask (opaque everywhere) or an empty view: nothing to carve with
            w2c = torch.linalg.inv(c2w[k].to(dev).float())
            p = centres @ w2c[:3, :3].T + w2c[:3, 3]
            z = -p[:, 2]  # distance along the view axis (OpenGL cameras look along -z)
            fx, fy, cx, cy = (float(v) for v in intrinsics[k])
            front = z > 1e-6
            zs = z.clamp_min(1e-6)
            u = fx * p[:, 0] / zs + cx
            v = cy - fy * p[:, 1] / zs
            # A cell stays when a mask pixel lies within its own projected radius (plus a pixel): the
            # distance from each pixel to the nearest mask pixel, compared per cell.
            dist = torch.from_numpy(distance_transform_edt(~mask.cpu().numpy())).to(dev, torch.float32)
            r_px = max(fx, fy) * radius / zs + 1.0
            ui, vi = u.floor().long(), v.floor().long()
            inside = front & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
            hit = torch.zeros_like(keep)
            hit[inside] = dist[vi[inside], ui[inside]] <= r_px[inside]
            # Cells the view does not see (outside its image or behind it) are not carved by it.
            keep &= hit | ~inside
        self.hull.copy_(keep)
        self.occupied.copy_(keep)
        return float(keep.float().mean())

    # -- rendering ----------------------------------------------------------------------------------
    def render_rays(
        self,
        origins: torch.Tensor,
        dirs: torch.Tensor,
        background: torch.Tensor | None = None,
        perturb: bool = False,
    ) -> RayOutput:
        """Render R rays: origins [R, 3] (metres), unit dirs [R, 3]. ``perturb`` jitters the samples.

        Without gradients (rendering) the march stops on each ray once its transmittance falls below
        ``min_transmittance`` (early ray termination); with gradients (training) every sample in the cube that
        the occupancy grid keeps is rendered, in one differentiable pass.
        """
        R, N = origins.shape[0], self.cfg.samples_per_ray
        dev = origins.device
        bg = self.background if background is None else background
        near, far = ray_box(origins, dirs, self.bound)
        offset = torch.rand(R, 1, device=dev) if perturb else torch.full((R, 1), 0.5, device=dev)
        if not torch.is_grad_enabled():
            return self._march(origins, dirs, near, far, offset, bg)
        dt = self.step_size
        t = near.unsqueeze(1) + (torch.arange(N, device=dev) + offset) * dt  # [R, N]
        valid = t < far.unsqueeze(1)
        # Cheap pre-selection by the cube, then the occupancy grid, before any network evaluation.
        ri, si = valid.nonzero(as_tuple=True)
        pos = origins[ri] + t[ri, si].unsqueeze(-1) * dirs[ri]
        keep = self.occupied[self._cell_index(pos)]
        ri, si, pos = ri[keep], si[keep], pos[keep]
        sigma = origins.new_zeros(R, N)
        rgb = origins.new_zeros(R, N, 3)
        if ri.numel() > 0:
            s, c = self.field(pos, dirs[ri])
            sigma = sigma.index_put((ri, si), s)
            rgb = rgb.index_put((ri, si), c)
        out = volume_render(sigma, rgb, t, valid.float() * dt, bg)
        return {"rgb": out["rgb"], "depth": out["depth"], "opacity": out["opacity"]}

    #: Samples per ray marched at once without gradients; rays that are opaque by then stop.
    march_segment: int = 32
    default_chunk = 1 << 16
    #: Transmittance below which a ray stops.
    min_transmittance: float = 1e-4

    @torch.no_grad()
    def _march(self, origins, dirs, near, far, offset, bg) -> RayOutput:
        """The same quadrature as ``volume_render``, segment by segment, dropping rays once opaque.

        Returns rgb [R, 3], depth [R] (distance), opacity [R] and t_stop [R], the distance after which the
        remaining samples carry less than ``min_transmittance`` of the light (inf for rays that never stop).
        """
        R, N, S, dt = origins.shape[0], self.cfg.samples_per_ray, self.march_segment, self.step_size
        dev = origins.device
        trans = torch.ones(R, device=dev)
        acc_rgb = torch.zeros(R, 3, device=dev)
        acc_t = torch.zeros(R, device=dev)
        t_stop = torch.full((R,), float("inf"), device=dev)
        active = (far > near).nonzero(as_tuple=True)[0]
        for start in range(0, N, S):
            if active.numel() == 0:
                break
            n = min(S, N - start)
            t = near[active, None] + (torch.arange(start, start + n, device=dev) + offset[active]) * dt  # [A, n]
            valid = t < far[active, None]
            ai, si = valid.nonzero(as_tuple=True)
            pos = origins[active[ai]] + t[ai, si].unsqueeze(-1) * dirs[active[ai]]
            keep = self.occupied[self._cell_index(pos)]
            ai, si, pos = ai[keep], si[keep], pos[keep]
            A = active.numel()
            tau = torch.zeros(A, n, device=dev)
            rgb = torch.zeros(A, n, 3, device=dev)
            if ai.numel() > 0:
                sg, c = self.field(pos, dirs[active[ai]])
                tau[ai, si] = sg * dt
                rgb[ai, si] = c
            t_before = trans[active]
            local = torch.exp(-(torch.cumsum(tau, dim=1) - tau)) * t_before.unsqueeze(1)  # transmittance
            w = (1.0 - torch.exp(-tau)) * local
            acc_rgb[active] += (w.unsqueeze(-1) * rgb).sum(1)
            acc_t[active] += (w * t).sum(1)
            t_after = t_before * torch.exp(-tau.sum(1))
            trans[active] = t_after
            done = t_after < self.min_transmittance
            if done.any():
                # The first sample after which the transmittance is below the threshold.
                below = (local * torch.exp(-tau)) < self.min_transmittance
                first = below.float().argmax(dim=1)
                t_stop[active[done]] = t[done].gather(1, first[done].unsqueeze(1))[:, 0]
            # Rays leave when opaque or when they have left the cube.
            active = active[~done & valid[:, -1]]
        opacity = 1.0 - trans
        depth = acc_t / opacity.clamp_min(1e-10)
        depth = torch.where(opacity > EMPTY_OPACITY, depth, torch.zeros_like(depth))
        rgb_out = acc_rgb + trans.unsqueeze(-1) * bg
        return {"rgb": rgb_out, "depth": depth, "opacity": opacity, "t_stop": t_stop}

    def param_groups(self, lr: float) -> list[dict]:
        """Optimizer groups: the hash table without weight decay, the MLPs with a little (Instant-NGP)."""
        return [
            {"params": [self.encoding.table], "lr": lr, "weight_decay": 0.0},
            {"params": [*self.density_net.parameters(), *self.color_net.parameters()], "lr": lr, "weight_decay": 1e-6},
        ]
