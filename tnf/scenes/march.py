"""Rendering without gradients by marching an occupancy grid: ``OccupancyMarch``, a mixin of a field scene.

A ray is sampled at ``near + (n + offset) * step_size`` (sample n, distances in metres), as the differentiable
pass samples it; only the samples in occupied cells, in front of where the ray turns opaque, reach the network.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from tnf.scenes.encoding import spherical_harmonics
from tnf.scenes.render import EMPTY_OPACITY, RayOutput, interval_termination, ray_aabb

FieldFn = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""Density [P] (1/metre) and colour [P, 3] in [0, 1] at positions [P, 3] (metres), given the spherical harmonics
[P, 16] of the view directions."""


class OccupancyMarch:
    """The march of a field scene with an occupancy grid, for rendering without gradients (``_march``).

    The scene holds ``cfg.samples_per_ray`` and ``cfg.occupancy_resolution`` (G), ``bound`` (metres), the step
    ``step_size`` (metres), the grid ``occupied`` [G^3] (bool, x-major), the counters ``march_stats``, and gives
    the field to render with (``_march_field``) and whether a Warp kernel runs (``_use_kernel``).
    """

    cfg: Any
    bound: float
    step_size: float
    occupied: torch.Tensor
    march_stats: dict[str, int]

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
    #: The march's sample selection by a Warp kernel (``hash_kernel.march_select``: one thread per ray, no
    #: [rays, window] tensors): None = as the scene's ``render_kernel``, False = PyTorch (``_select_window``).
    march_kernel: bool | None = None

    def _march_field(self, device: torch.device) -> FieldFn:
        """The field to render with on ``device`` (``FieldFn``)."""
        raise NotImplementedError

    def _use_kernel(self, device: torch.device, wanted: bool | None = None) -> bool:
        """Whether to run a Warp kernel on ``device``: ``wanted`` True, or None and Warp runs there."""
        raise NotImplementedError

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

        ``origins`` [R, 3] and unit ``dirs`` [R, 3] (metres), the cube's ``near`` and ``far`` [R] (metres),
        ``offset`` [R, 1] (steps) and the background ``bg`` [3] or [R, 3]. Returns rgb [R, 3], depth [R]
        (distance), opacity [R] and t_stop [R], the distance after which the remaining samples carry less than
        ``min_transmittance`` of the light (inf for rays that never stop).
        """
        R, dev = origins.shape[0], origins.device
        # Per ray: transmittance, accumulated colour (3) and accumulated distance.
        acc = torch.zeros(R, 5, device=dev)
        acc[:, 0] = 1.0
        t_stop = torch.full((R,), float("inf"), device=dev)
        self.march_stats["rays"] += R
        box = self._occupied_box()
        if box is not None and R > 0:
            self._march_rounds(origins, dirs, near, far, offset, box, acc, t_stop)
        return _ray_output(acc, bg, t_stop)

    def _march_rounds(
        self,
        origins: torch.Tensor,
        dirs: torch.Tensor,
        near: torch.Tensor,
        far: torch.Tensor,
        offset: torch.Tensor,
        box: tuple[torch.Tensor, torch.Tensor],
        acc: torch.Tensor,
        t_stop: torch.Tensor,
    ) -> None:
        """March the rays that cross ``box`` in rounds until each is opaque or has left it, filling their rows
        of ``acc`` [R, 5] (transmittance, colour, distance) and ``t_stop`` [R] in place."""
        N, dev = self.cfg.samples_per_ray, origins.device
        field = self._march_field(dev)
        budget = self.march_budget if self.march_budget is not None else 1 << (25 if dev.type == "cuda" else 20)
        kernel = self._use_kernel(dev, self.march_kernel)
        occ_u8 = self.occupied.to(torch.uint8) if kernel else None
        act, ray, state = self._rays_in_box(origins, dirs, near, far, offset, box, acc)
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
            if occ_u8 is not None:
                ai, slot, t_chosen = self._select_kernel(ray, state, occ_u8, K)
            else:
                ai, slot, t_chosen = self._select_window(ray, state, W, K)
            stats["samples"] += ai.numel()
            tau, rgb, ts = self._round_samples(field, ray, ai, slot, t_chosen, A, K)
            opaque, stop = self._composite(state, tau, rgb, ts, ray[:, 8:9])
            acc[act] = state[:, 2:]
            t_stop[act] = torch.where(opaque, stop, t_stop[act])
            go = (~opaque & (state[:, 0] < state[:, 1])).nonzero()[:, 0]
            act, ray, state = act[go], ray[go], state[go]

    def _rays_in_box(
        self,
        origins: torch.Tensor,
        dirs: torch.Tensor,
        near: torch.Tensor,
        far: torch.Tensor,
        offset: torch.Tensor,
        box: tuple[torch.Tensor, torch.Tensor],
        acc: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The rays that cross ``box`` and what a march round needs of each.

        Returns their indices ``act`` [A], ``ray`` [A, 25] = origin (3), direction (3), near, far, offset, the
        direction's spherical harmonics (16); and ``state`` [A, 7] = next and end sample numbers (floats: exact
        below 2^24), then their rows of ``acc``. Packed so that dropping rays is one indexing per tensor.
        """
        N, dt = self.cfg.samples_per_ray, self.step_size
        # Sample numbers [first, end) of each ray that lie in the occupied box, with a sample of margin:
        # samples outside it are in empty cells, which the dense pass skips too.
        box_in, box_out = ray_aabb(origins, dirs, box[0], box[1])
        off = offset[:, 0]
        first = (((box_in - near) / dt - off).floor() - 1).clamp(0, N)
        end = (((torch.minimum(box_out, far) - near) / dt - off).ceil() + 1).clamp(0, N)
        act = ((box_out > box_in) & (end > first)).nonzero()[:, 0]
        o, d = origins[act], dirs[act]
        ray = torch.cat([o, d, near[act, None], far[act, None], off[act, None], spherical_harmonics(d)], 1)
        state = torch.cat([first[act, None], end[act, None], acc[act]], dim=1)
        return act, ray, state

    def _select_kernel(
        self, ray: torch.Tensor, state: torch.Tensor, occ_u8: torch.Tensor, K: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A march round's samples by the Warp kernel: one thread per ray steps to its next K occupied samples
        (no window: it looks as far as it needs) and advances ``state[:, 0]`` in place. Returns what
        ``_select_window`` returns."""
        from tnf.scenes import hash_kernel

        t_sel, count = hash_kernel.march_select(ray, state, occ_u8, self.bound, self.step_size, K)
        ai, slot = (torch.arange(K, device=ray.device) < count[:, None]).nonzero(as_tuple=True)
        return ai, slot, t_sel[ai, slot]

    def _select_window(
        self, ray: torch.Tensor, state: torch.Tensor, W: int, K: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A march round's samples in PyTorch: each ray's first K occupied samples among its next W.

        Returns the ray of each chosen sample (row of ``ray``), its slot (rank among the ray's chosen ones) and
        its distance; advances ``state[:, 0]`` (next sample number) past the K-th chosen sample, or past the
        window when it held fewer. ``ray`` and ``state`` as ``_rays_in_box`` packs them.
        """
        dt, G, b = self.step_size, self.cfg.occupancy_resolution, self.bound
        cell_stride = torch.tensor([G * G, G, 1], device=ray.device, dtype=torch.int32)
        o, d, n0, n1, off_a = ray[:, 0:3], ray[:, 3:6], ray[:, 6:7], ray[:, 7:8], ray[:, 8:9]
        ptr, end_a = state[:, 0:1], state[:, 1:2]
        ar = torch.arange(W, device=ray.device, dtype=torch.float32)
        j = ptr + ar  # [A, W] sample numbers
        t = n0 + (j + off_a) * dt
        # Occupancy of each sample: the arithmetic of the scene's cell index.
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

    def _round_samples(
        self,
        field: FieldFn,
        ray: torch.Tensor,
        ai: torch.Tensor,
        slot: torch.Tensor,
        t_chosen: torch.Tensor,
        A: int,
        K: int,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The field at a round's chosen samples (ray ``ai``, slot ``slot``, distance ``t_chosen``), in chunks of
        ``field_chunk``: optical depth ``tau`` [A, K], colour [A, K, 3] and distance [A, K] (metres) per slot;
        zero in slots that hold no sample."""
        dev, dt = ray.device, self.step_size
        o, d, sh = ray[:, 0:3], ray[:, 3:6], ray[:, 9:]
        tau = torch.zeros(A, K, device=dev)
        rgb = torch.zeros(A, K, 3, device=dev)
        ts = torch.zeros(A, K, device=dev)
        for c in range(0, ai.numel(), self.field_chunk):
            a, k = ai[c : c + self.field_chunk], slot[c : c + self.field_chunk]
            tk = t_chosen[c : c + self.field_chunk]
            sg, rg = field(o[a] + tk.unsqueeze(-1) * d[a], sh[a])
            tau[a, k] = sg * dt
            rgb[a, k] = rg
            ts[a, k] = tk
        return tau, rgb, ts

    def _composite(
        self, state: torch.Tensor, tau: torch.Tensor, rgb: torch.Tensor, ts: torch.Tensor, off_a: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Composite a round's K slots into ``state`` (in place), continuing the transmittance each ray brought
        into the round. ``off_a`` [A, 1]: each ray's sample offset (steps). Returns which rays turned opaque [A]
        and where each stopped [A] (metres): its first sample after which the transmittance is too low."""
        dt = self.step_size
        tr = state[:, 2]
        # Eq. 1 over the K slots.
        csum = tau.cumsum(1)
        local = torch.exp(-(csum - tau)) * tr[:, None]
        w = (1.0 - torch.exp(-tau)) * local
        state[:, 3:6] += (w.unsqueeze(-1) * rgb).sum(1)
        # Expected termination distance as in ``volume_render`` (each interval begins offset steps
        # before its sample; empty slots have zero weight).
        state[:, 6] += (w * (ts - off_a * dt + dt * interval_termination(tau))).sum(1)
        state[:, 2] = tr * torch.exp(-csum[:, -1])
        opaque = state[:, 2] < self.min_transmittance
        below = local * torch.exp(-tau) < self.min_transmittance
        stop = ts.gather(1, below.float().argmax(1, keepdim=True))[:, 0]
        return opaque, stop


def _ray_output(acc: torch.Tensor, bg: torch.Tensor, t_stop: torch.Tensor) -> RayOutput:
    """The rays' rgb [R, 3] (over ``bg``), depth [R] (metres, 0 where empty), opacity [R] and ``t_stop`` [R] from
    their accumulated transmittance, colour and distance ``acc`` [R, 5]."""
    trans, acc_rgb, acc_t = acc[:, 0], acc[:, 1:4], acc[:, 4]
    opacity = 1.0 - trans
    depth = acc_t / opacity.clamp_min(1e-10)
    depth = torch.where(opacity > EMPTY_OPACITY, depth, torch.zeros_like(depth))
    rgb_out = acc_rgb + trans.unsqueeze(-1) * bg
    return {"rgb": rgb_out, "depth": depth, "opacity": opacity, "t_stop": t_stop}
