"""``hashgrid``: a multiresolution hash encoding (Instant-NGP) with small MLPs, in pure PyTorch.

The object sits in the cube [-bound, bound]^3 around the origin. Rays are marched with a fixed step
(``samples_per_ray`` steps across the cube's diagonal); an occupancy grid, refreshed during training from
the field's own density, removes samples in empty space before the network sees them, so only the few
samples near the surface cost a hash-grid lookup. The encoding and the MLPs are in ``tnf.scenes.encoding``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import torch

from tnf.registry import FROM_YAML, yaml_defaults
from tnf.scenes.encoding import PRIMES, HashEncoding, gather_rows, mlp, spherical_harmonics
from tnf.scenes.render import (
    EMPTY_OPACITY,
    FieldScene,
    RayOutput,
    distortion_loss,
    interval_termination,
    ray_aabb,
    ray_box,
    volume_render,
)

# The encoding's names stay importable from here.
__all__ = ["PRIMES", "HashEncoding", "HashGridScene", "gather_rows", "mlp", "spherical_harmonics"]


class HashGridScene(FieldScene):
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
    #: Transmittance below which a ray stops (early ray termination).
    min_transmittance: float = 1e-4
    #: Samples per ray whose occupancy a march round looks up at least (a cheap test, no network; the
    #: PyTorch selection only: the Warp kernel looks as far as each ray needs).
    march_window: int = 64
    #: Occupied samples per ray a march round sends to the network at least.
    march_samples: int = 16
    #: Samples looked up per round over all rays; rounds with fewer rays left look further along each
    #: (fewer rounds, which matters on a GPU). None: 2^25 on CUDA, 2^20 on the CPU. PyTorch selection only.
    march_budget: int | None = None
    #: Samples per network evaluation while rendering (bounds the hash encoding's memory).
    field_chunk: int = 1 << 19
    #: Half precision (float16) for the hash table and MLPs while rendering: None = on CUDA only.
    render_half: bool | None = None
    #: The hash encoding by one Warp kernel while rendering (``hash_kernel``; far less memory traffic than
    #: the PyTorch encoding's [P, L, 8] tensors): None = wherever Warp runs, else the PyTorch encoding.
    render_kernel: bool | None = None
    #: The march's sample selection by a Warp kernel (``hash_kernel.march_select``: one thread per ray, no
    #: [rays, window] tensors): None = as ``render_kernel``, False = PyTorch (``_select_window``).
    march_kernel: bool | None = None
    #: Compile the rendering field with ``torch.compile`` (fuses the hash encoding's element-wise work on
    #: CUDA); falls back to eager with a warning when compiling fails. Off by default: compiling takes
    #: a while on the first render.
    render_compile: bool = False

    def _occupied_box(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Corners [3], [3] (metres) of the box around the occupied cells; None when none is occupied.

        Cached until the occupancy grid changes (training refreshes it; loading a checkpoint replaces it).
        """
        key = (self.occupied.data_ptr(), self.occupied._version, self.bound)
        cached = getattr(self, "_box_cache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        G = self.cfg.occupancy_resolution
        cells = self.occupied.view(G, G, G).nonzero()
        box = None
        if cells.numel() > 0:
            size = 2.0 * self.bound / G
            box = (cells.amin(0) * size - self.bound, (cells.amax(0) + 1) * size - self.bound)
            box = (box[0].float(), box[1].float())
        self._box_cache = (key, box)
        return box

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
        from tnf.scenes import hash_kernel  # lazy: imports warp

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

    @torch.no_grad()
    def _march(self, origins, dirs, near, far, offset, bg) -> RayOutput:
        """The quadrature of ``volume_render`` over the same samples as the differentiable pass (sample n of
        a ray at ``near + (n + offset) * step_size``), evaluating only what can change the result.

        Rays that miss the box around the occupied cells are empty. The others are marched in rounds: a
        round finds the next ``march_samples`` occupied samples of every ray (twice as many each round; a
        Warp kernel steps along each ray, the PyTorch fallback looks up a window of at least
        ``march_window`` samples at once), sends them to the network in one batch, composites them in order,
        and drops the rays whose transmittance fell below ``min_transmittance`` or that left the box. So the
        network sees only occupied samples in front of each ray's surface, and the count of operations depends
        on the rounds, not the samples.

        Returns rgb [R, 3], depth [R] (distance), opacity [R] and t_stop [R], the distance after which the
        remaining samples carry less than ``min_transmittance`` of the light (inf for rays that never stop).
        """
        R, N, dt = origins.shape[0], self.cfg.samples_per_ray, self.step_size
        dev = origins.device
        # Per ray: transmittance, accumulated colour (3) and accumulated distance.
        acc = torch.zeros(R, 5, device=dev)
        acc[:, 0] = 1.0
        t_stop = torch.full((R,), float("inf"), device=dev)
        self.march_stats["rays"] += R
        box = self._occupied_box()
        if box is not None and R > 0:
            half = self.render_half if self.render_half is not None else dev.type == "cuda"
            table = self._render_table(half)
            budget = self.march_budget if self.march_budget is not None else 1 << (25 if dev.type == "cuda" else 20)
            G, b = self.cfg.occupancy_resolution, self.bound
            cell_stride = torch.tensor([G * G, G, 1], device=dev, dtype=torch.int32)
            kernel = self._use_kernel(dev, self.march_kernel)
            if kernel:
                from tnf.scenes import hash_kernel

                occ_u8 = self.occupied.to(torch.uint8)
            # Sample numbers [first, end) of each ray that lie in the occupied box, with a sample of margin:
            # samples outside it are in empty cells, which the dense pass skips too.
            box_in, box_out = ray_aabb(origins, dirs, box[0], box[1])
            off = offset[:, 0]
            first = (((box_in - near) / dt - off).floor() - 1).clamp(0, N)
            end = (((torch.minimum(box_out, far) - near) / dt - off).ceil() + 1).clamp(0, N)
            act = ((box_out > box_in) & (end > first)).nonzero()[:, 0]
            # What a round needs of each active ray, packed so that dropping rays is one indexing per
            # tensor: ray = origin (3), direction (3), near, far, offset, the direction's spherical
            # harmonics (16); state = next and end sample numbers (floats: exact below 2^24), then ``acc``.
            o, d = origins[act], dirs[act]
            ray = torch.cat([o, d, near[act, None], far[act, None], off[act, None], spherical_harmonics(d)], 1)
            state = torch.cat([first[act, None], end[act, None], acc[act]], dim=1)
            stats = self.march_stats
            stats["marched_rays"] += act.numel()
            rounds = 0
            while act.numel() > 0:
                A = act.numel()
                stats["rounds"] += 1
                # Rays still going after a round are seldom opaque: each round sends twice the samples
                # of the last (so at most twice what a ray needs), and looks further when few rays are left.
                W = int(min(N, max(self.march_window, budget // A)))
                K = int(min(N if kernel else W, self.march_samples << min(rounds, 16)))
                rounds += 1
                o, d, off_a, sh = ray[:, 0:3], ray[:, 3:6], ray[:, 8:9], ray[:, 9:]
                tr = state[:, 2]
                if kernel:
                    # One thread per ray steps to its next K occupied samples (no window: it looks as far as
                    # it needs); the next sample number is advanced in place.
                    t_sel, count = hash_kernel.march_select(ray, state, occ_u8, b, dt, K)
                    ai, slot = (torch.arange(K, device=dev) < count[:, None]).nonzero(as_tuple=True)
                    t_chosen = t_sel[ai, slot]
                else:
                    ai, slot, t_chosen = self._select_window(ray, state, W, K, cell_stride)
                stats["samples"] += ai.numel()
                tau = torch.zeros(A, K, device=dev)
                rgb = torch.zeros(A, K, 3, device=dev)
                ts = torch.zeros(A, K, device=dev)
                for c in range(0, ai.numel(), self.field_chunk):
                    a, k = ai[c : c + self.field_chunk], slot[c : c + self.field_chunk]
                    tk = t_chosen[c : c + self.field_chunk]
                    sg, rg = self._eval_field(o[a] + tk.unsqueeze(-1) * d[a], sh[a], table, half)
                    tau[a, k] = sg * dt
                    rgb[a, k] = rg
                    ts[a, k] = tk
                # Eq. 1 over the K slots, continuing the transmittance the ray brought into this round.
                csum = tau.cumsum(1)
                local = torch.exp(-(csum - tau)) * tr[:, None]
                w = (1.0 - torch.exp(-tau)) * local
                state[:, 3:6] += (w.unsqueeze(-1) * rgb).sum(1)
                # Expected termination distance as in ``volume_render`` (each interval begins offset steps
                # before its sample; empty slots have zero weight).
                state[:, 6] += (w * (ts - off_a * dt + dt * interval_termination(tau))).sum(1)
                state[:, 2] = tr * torch.exp(-csum[:, -1])
                opaque = state[:, 2] < self.min_transmittance
                # Where an opaque ray stopped: its first sample after which the transmittance is too low.
                below = local * torch.exp(-tau) < self.min_transmittance
                stop = ts.gather(1, below.float().argmax(1, keepdim=True))[:, 0]
                acc[act] = state[:, 2:]
                t_stop[act] = torch.where(opaque, stop, t_stop[act])
                go = (~opaque & (state[:, 0] < state[:, 1])).nonzero()[:, 0]
                act, ray, state = act[go], ray[go], state[go]
        trans, acc_rgb, acc_t = acc[:, 0], acc[:, 1:4], acc[:, 4]
        opacity = 1.0 - trans
        depth = acc_t / opacity.clamp_min(1e-10)
        depth = torch.where(opacity > EMPTY_OPACITY, depth, torch.zeros_like(depth))
        rgb_out = acc_rgb + trans.unsqueeze(-1) * bg
        return {"rgb": rgb_out, "depth": depth, "opacity": opacity, "t_stop": t_stop}

    def _select_window(
        self, ray: torch.Tensor, state: torch.Tensor, W: int, K: int, cell_stride: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A march round's samples in PyTorch: each ray's first K occupied samples among its next W.

        Returns the ray of each chosen sample (row of ``ray``), its slot (rank among the ray's chosen ones) and
        its distance; advances ``state[:, 0]`` (next sample number) past the K-th chosen sample, or past the
        window when it held fewer. ``ray`` and ``state`` as in ``_march``.
        """
        dt, G, b = self.step_size, self.cfg.occupancy_resolution, self.bound
        o, d, n0, n1, off_a = ray[:, 0:3], ray[:, 3:6], ray[:, 6:7], ray[:, 7:8], ray[:, 8:9]
        ptr, end_a = state[:, 0:1], state[:, 1:2]
        ar = torch.arange(W, device=ray.device, dtype=torch.float32)
        j = ptr + ar  # [A, W] sample numbers
        t = n0 + (j + off_a) * dt
        # Occupancy of each sample: the arithmetic of ``_cell_index``.
        pos = o.unsqueeze(1) + t.unsqueeze(-1) * d.unsqueeze(1)
        cell = ((pos + b) / (2.0 * b) * G).to(torch.int32).clamp_(0, G - 1)
        occ = self.occupied[(cell * cell_stride).sum(-1)] & (j < end_a) & (t < n1)
        del pos, cell
        # The first K occupied samples of each ray, in order: slot = their rank among them.
        rank = occ.cumsum(1, dtype=torch.int32)
        sel = occ & (rank <= K)
        ai, si = sel.nonzero(as_tuple=True)
        slot = (rank[ai, si] - 1).long()
        # The next round starts after the K-th occupied sample, or after the window if it had fewer.
        last = torch.where(sel, ar + 1, 0).amax(1)
        state[:, 0] += torch.where(rank[:, -1] > K, last, W)
        return ai, slot, t[ai, si]

    def param_groups(self, lr: float) -> list[dict]:
        """Optimizer groups: the hash table without weight decay, the MLPs with a little (Instant-NGP)."""
        return [
            {"params": [self.encoding.table], "lr": lr, "weight_decay": 0.0},
            {"params": [*self.density_net.parameters(), *self.color_net.parameters()], "lr": lr, "weight_decay": 1e-6},
        ]
