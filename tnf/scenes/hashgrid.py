"""``hashgrid``: a multiresolution hash encoding (Instant-NGP) with small MLPs, in pure PyTorch.

The object sits in the cube [-bound, bound]^3 around the origin. Rays are marched with a fixed step
(``samples_per_ray`` steps across the cube's diagonal); an occupancy grid, refreshed during training from
the field's own density, removes samples in empty space before the network sees them, so only the few
samples near the surface cost a hash-grid lookup. The encoding and the MLPs are in ``tnf.scenes.encoding``, the
march that renders without gradients in ``tnf.scenes.march``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch

from tnf.registry import FROM_YAML, yaml_defaults
from tnf.scenes.encoding import PRIMES, HashEncoding, gather_rows, mlp, spherical_harmonics
from tnf.scenes.march import FieldFn, OccupancyMarch
from tnf.scenes.render import (
    FieldScene,
    RayOutput,
    distortion_loss,
    ray_box,
    volume_render,
)

# The encoding's names stay importable from here.
__all__ = ["PRIMES", "HashEncoding", "HashGridScene", "gather_rows", "mlp", "spherical_harmonics"]


class HashGridScene(OccupancyMarch, FieldScene):
    """Instant-NGP style hash-grid radiance field with an occupancy grid (pure PyTorch, CPU or CUDA)."""

    # Buffers registered in ``__init__`` (declared here for type checkers).
    occ_density: torch.Tensor
    occupied: torch.Tensor
    hull: torch.Tensor

    @dataclass
    @yaml_defaults("scene/hashgrid")
    class Config:
        levels: int = FROM_YAML
        """Number of hash-grid levels."""
        features_per_level: int = FROM_YAML
        """Features stored per grid vertex and level."""
        log2_table_size: int = FROM_YAML
        """log2 of the entries per level's hash table (19 -> 524288)."""
        base_resolution: int = FROM_YAML
        """Cells per axis of the coarsest level."""
        max_resolution: int = FROM_YAML
        """Cells per axis of the finest level."""
        hidden: int = FROM_YAML
        """Width of the density and colour MLPs."""
        geo_features: int = FROM_YAML
        """Features the density MLP passes to the colour MLP."""
        density_layers: int = FROM_YAML
        """Hidden layers of the density MLP."""
        color_layers: int = FROM_YAML
        """Hidden layers of the colour MLP."""
        samples_per_ray: int = FROM_YAML
        """Ray-marching steps across the cube's diagonal (step = 2 sqrt(3) bound / samples_per_ray)."""
        occupancy_resolution: int = FROM_YAML
        """Cells per axis of the occupancy grid."""
        occupancy_threshold: float = FROM_YAML
        """A cell is empty when a step through it would absorb less than this fraction of light."""
        occupancy_update_every: int = FROM_YAML
        """Training steps between occupancy-grid refreshes."""
        occupancy_warmup: int = FROM_YAML
        """Training steps before empty cells start being skipped."""
        occupancy_decay: float = FROM_YAML
        """Decay of the grid's running density at each refresh (forgets floaters that training removes)."""
        bound: float | None = FROM_YAML
        """Half-size of the cube [-bound, bound]^3 around the origin that holds the object, metres;
        null: derived from the training cameras when fitting."""
        background: tuple[float, float, float] = FROM_YAML
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
        #: Counts of the rendering march, accumulated (reset it to measure): rays rendered, rays that reach
        #: the occupied box, march rounds, samples sent to the network.
        self.march_stats = {"rays": 0, "marched_rays": 0, "rounds": 0, "samples": 0}

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
        delta = valid.float() * dt
        # Sample n's interval begins ``offset`` steps before it.
        out = volume_render(sigma, rgb, t, delta, bg, start=t - offset * dt)
        # The distortion loss in units of the cube's size, for fitting (``FitSettings.distortion_weight``).
        dist = distortion_loss(out["weights"], t, delta) / (2.0 * self.bound)
        return {"rgb": out["rgb"], "depth": out["depth"], "opacity": out["opacity"], "distortion": dist}

    # -- rendering without gradients -----------------------------------------------------------------
    #: Rays per rendering chunk (32 frames of 128 x 128).
    default_chunk = 1 << 19
    #: Half precision (float16) for the hash table and MLPs while rendering: None = on CUDA only.
    render_half: bool | None = None
    #: The hash encoding by one Warp kernel while rendering (``hash_kernel``; far less memory traffic than
    #: the PyTorch encoding's [P, L, 8] tensors): None = wherever Warp runs, else the PyTorch encoding.
    render_kernel: bool | None = None
    #: Compile the rendering field with ``torch.compile`` (fuses the hash encoding's element-wise work on
    #: CUDA); falls back to eager with a warning when compiling fails. Off by default: compiling takes
    #: a while on the first render.
    render_compile: bool = False

    def _render_table(self, half: bool) -> torch.Tensor:
        """The hash table to render with: a float16 copy (kept until the table changes) or the table."""
        table = self.encoding.table
        if not half:
            return table.detach()
        key = (table.data_ptr(), table._version, table.device)
        cached = getattr(self, "_half_table", None)
        if cached is None or cached[0] != key:
            cached = (key, table.detach().half())
            self._half_table = cached
        return cached[1]

    def _render_field(
        self, pos: torch.Tensor, sh: torch.Tensor, table: torch.Tensor, half: bool
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``field`` without gradients: density [P] and colour [P, 3] (float32) at positions [P, 3], with the
        spherical harmonics of the view directions [P, 16] computed once per ray by the caller."""
        x = self._normalise(pos)
        with torch.autocast(pos.device.type, dtype=torch.float16, enabled=half):
            if self._use_kernel(pos.device):
                from tnf.scenes.hash_kernel import hash_encode

                enc = self.encoding
                features = hash_encode(x, table, enc.res, enc.n_dense, enc.table_size)
            else:
                features = self.encoding(x, table)
            h = self.density_net(features)
            rgb = self.color_net(torch.cat([sh.to(h.dtype), h[:, 1:]], dim=-1))
        sigma = torch.exp((h[:, 0].float() - 1.0).clamp(max=15.0))
        return sigma, torch.sigmoid(rgb.float())

    def _use_kernel(self, device: torch.device, wanted: bool | None = None) -> bool:
        """Whether to render with a Warp kernel: ``wanted`` (default ``render_kernel``) True, or None and Warp
        runs on ``device``."""
        wanted = self.render_kernel if wanted is None else wanted
        if wanted is False:
            return False
        try:
            from tnf.scenes import hash_kernel  # lazy: imports warp
        except ImportError:  # Warp is not installed, or cannot load here: the PyTorch encoding renders
            ok = False
        else:
            ok = hash_kernel.available(device)
        if wanted and not ok:
            raise RuntimeError(f"a Warp kernel was asked for but Warp cannot run on {device}")
        return ok

    def _field_fn(self) -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
        """``_render_field``, compiled once when ``render_compile`` is set."""
        if not self.render_compile:
            return self._render_field
        fn = getattr(self, "_compiled_field", None)
        if fn is None:
            fn = torch.compile(self._render_field, dynamic=True)
            self._compiled_field = fn
        return fn

    def _march_field(self, device: torch.device) -> FieldFn:
        """The field the march renders with on ``device``: ``_render_field`` in half precision where
        ``render_half`` (None: on CUDA), with the hash table it needs looked up once."""
        half = self.render_half if self.render_half is not None else device.type == "cuda"
        table = self._render_table(half)
        return lambda pos, sh: self._eval_field(pos, sh, table, half)

    def _eval_field(self, pos, sh, table, half) -> tuple[torch.Tensor, torch.Tensor]:
        fn = self._field_fn()
        if fn is self._render_field:
            return fn(pos, sh, table, half)
        try:
            return fn(pos, sh, table, half)
        except Exception as e:  # a compiler or backend failure must not stop rendering
            msg = f"torch.compile of the hash-grid field failed ({type(e).__name__}: {e}); rendering eagerly"
            warnings.warn(msg, stacklevel=2)
            self.render_compile = False
            return self._render_field(pos, sh, table, half)

    def param_groups(self, lr: float) -> list[dict]:
        """Optimizer groups: the hash table without weight decay, the MLPs with a little (Instant-NGP)."""
        return [
            {"params": [self.encoding.table], "lr": lr, "weight_decay": 0.0},
            {"params": [*self.density_net.parameters(), *self.color_net.parameters()], "lr": lr, "weight_decay": 1e-6},
        ]
