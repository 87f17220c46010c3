"""``nerf``: the original NeRF (Mildenhall et al. 2020) inside a bounded cube around the object.

Positional encoding of position and view direction, an MLP of ``depth`` x ``width`` with a skip connection
that feeds the encoded input back in the middle, and two networks: a coarse one sampled uniformly
(stratified) along each ray and a fine one sampled where the coarse weights say the surface is
(hierarchical sampling). Both are trained; the fine one renders.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from tnf.registry import FROM_YAML, yaml_defaults
from tnf.scenes.render import FieldScene, RayOutput, ray_box, volume_render


def positional_encoding(x: torch.Tensor, freqs: int) -> torch.Tensor:
    """``[x, sin(2^k pi x), cos(2^k pi x)]`` for k < freqs: [..., D] -> [..., D (1 + 2 freqs)]."""
    scales = (2.0 ** torch.arange(freqs, device=x.device, dtype=x.dtype)) * math.pi
    xb = (x.unsqueeze(-1) * scales).flatten(-2)  # [..., D * freqs]
    return torch.cat([x, torch.sin(xb), torch.cos(xb)], dim=-1)


class NerfMLP(nn.Module):
    """NeRF's MLP: encoded position -> density and a feature; feature + encoded direction -> colour."""

    def __init__(self, pos_dim: int, dir_dim: int, depth: int, width: int, skip: int):
        super().__init__()
        self.skip = skip
        layers = []
        d = pos_dim
        for i in range(depth):
            if i == skip and i > 0:
                d += pos_dim
            layers.append(nn.Linear(d, width))
            d = width
        self.layers = nn.ModuleList(layers)
        self.sigma = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.color = nn.Sequential(
            nn.Linear(width + dir_dim, width // 2), nn.ReLU(inplace=True), nn.Linear(width // 2, 3)
        )

    def forward(self, xe: torch.Tensor, de: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Encoded positions [P, pos_dim] and directions [P, dir_dim] -> density [P] (1/metre), rgb [P, 3]."""
        h = xe
        for i, layer in enumerate(self.layers):
            if i == self.skip and i > 0:
                h = torch.cat([h, xe], dim=-1)
            h = F.relu(layer(h))
        # Softplus rather than ReLU: a ReLU density that goes negative everywhere never recovers.
        sigma = F.softplus(self.sigma(h)[:, 0] - 1.0)
        rgb = torch.sigmoid(self.color(torch.cat([self.feature(h), de], dim=-1)))
        return sigma, rgb


def sample_pdf(edges: torch.Tensor, weights: torch.Tensor, n: int, deterministic: bool) -> torch.Tensor:
    """Inverse-transform samples [R, n] of the piecewise-constant pdf ``weights`` [R, B] on ``edges`` [R, B+1]."""
    w = weights + 1e-5  # no zero-probability bins: keeps the CDF strictly increasing
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], dim=-1)  # [R, B+1]
    R = edges.shape[0]
    if deterministic:
        u = torch.linspace(0.0, 1.0, n + 2, device=edges.device)[1:-1].expand(R, n)
    else:
        u = torch.rand(R, n, device=edges.device)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[1] - 1)
    c0, c1 = cdf.gather(1, idx - 1), cdf.gather(1, idx)
    e0, e1 = edges.gather(1, idx - 1), edges.gather(1, idx)
    frac = (u - c0) / (c1 - c0).clamp_min(1e-10)
    return e0 + frac * (e1 - e0)


class NerfScene(FieldScene):
    """Original NeRF: positional encoding, 8x256 MLP with skip, coarse + fine hierarchical sampling."""

    @dataclass
    @yaml_defaults("scene/nerf")
    class Config:
        depth: int = FROM_YAML
        """Layers of the position MLP."""
        width: int = FROM_YAML
        """Width of the position MLP (the colour branch has width / 2)."""
        skip: int = FROM_YAML
        """Layer that receives the encoded position again (0 = no skip)."""
        pos_freqs: int = FROM_YAML
        """Positional-encoding frequencies of the position (normalised by bound)."""
        dir_freqs: int = FROM_YAML
        """Positional-encoding frequencies of the view direction."""
        samples_coarse: int = FROM_YAML
        """Stratified samples per ray for the coarse network."""
        samples_fine: int = FROM_YAML
        """Extra samples per ray drawn from the coarse weights for the fine network (0 = coarse only)."""
        bound: float | None = FROM_YAML
        """Half-size of the cube [-bound, bound]^3 around the origin that holds the object, metres;
        null: derived from the training cameras when fitting."""
        background: tuple[float, float, float] = FROM_YAML
        """RGB colour in [0, 1] behind the object."""

        def validate(self) -> None:
            if self.depth < 1 or self.width < 2:
                raise ValueError(f"depth must be >= 1 and width >= 2, got {self.depth}, {self.width}")
            if self.samples_coarse < 2 or self.samples_fine < 0:
                raise ValueError("samples_coarse must be >= 2 and samples_fine >= 0")
            if self.bound is not None and self.bound <= 0:
                raise ValueError(f"bound must be > 0 metres, got {self.bound}")

    default_chunk = 1 << 13

    def __init__(self, cfg: Config):
        if cfg.bound is None:
            raise ValueError("nerf scene needs a bound; fitting derives it from the cameras")
        super().__init__(cfg.bound, cfg.background)
        self.cfg = cfg
        pos_dim = 3 * (1 + 2 * cfg.pos_freqs)
        dir_dim = 3 * (1 + 2 * cfg.dir_freqs)
        self.coarse = NerfMLP(pos_dim, dir_dim, cfg.depth, cfg.width, cfg.skip)
        self.fine = NerfMLP(pos_dim, dir_dim, cfg.depth, cfg.width, cfg.skip) if cfg.samples_fine > 0 else None

    def _run(self, net: NerfMLP, origins, dirs, t, delta, bg):
        pos = origins.unsqueeze(1) + t.unsqueeze(-1) * dirs.unsqueeze(1)  # [R, N, 3]
        R, N = t.shape
        xe = positional_encoding(pos.reshape(-1, 3) / self.bound, self.cfg.pos_freqs)
        de = positional_encoding(dirs, self.cfg.dir_freqs).repeat_interleave(N, dim=0)
        sigma, rgb = net(xe, de)
        return volume_render(sigma.view(R, N), rgb.view(R, N, 3), t, delta, bg)

    def render_rays(
        self,
        origins: torch.Tensor,
        dirs: torch.Tensor,
        background: torch.Tensor | None = None,
        perturb: bool = False,
    ) -> RayOutput:
        """Render R rays: origins [R, 3] (metres), unit dirs [R, 3]. ``perturb`` stratifies the samples."""
        R, Nc = origins.shape[0], self.cfg.samples_coarse
        bg = self.background if background is None else background
        near, far = ray_box(origins, dirs, self.bound)
        far = torch.maximum(far, near)  # a miss gets zero-length intervals: nothing absorbs
        s = torch.linspace(0.0, 1.0, Nc + 1, device=origins.device)
        edges = near.unsqueeze(1) + s * (far - near).unsqueeze(1)  # [R, Nc + 1]
        u = torch.rand(R, Nc, device=origins.device) if perturb else torch.full((R, Nc), 0.5, device=origins.device)
        t_c = edges[:, :-1] + u * (edges[:, 1:] - edges[:, :-1])
        coarse = self._run(self.coarse, origins, dirs, t_c, edges[:, 1:] - edges[:, :-1], bg)
        if self.fine is None:
            return {"rgb": coarse["rgb"], "depth": coarse["depth"], "opacity": coarse["opacity"]}
        t_f = sample_pdf(edges, coarse["weights"].detach(), self.cfg.samples_fine, deterministic=not perturb)
        t_all, _ = torch.sort(torch.cat([t_c, t_f.detach()], dim=1), dim=1)
        # Each sample owns the interval up to the next one; the last one up to the exit.
        delta = torch.cat([t_all[:, 1:] - t_all[:, :-1], (far.unsqueeze(1) - t_all[:, -1:]).clamp_min(0)], dim=1)
        fine = self._run(self.fine, origins, dirs, t_all, delta, bg)
        return {"rgb": fine["rgb"], "depth": fine["depth"], "opacity": fine["opacity"], "rgb_coarse": coarse["rgb"]}

    def param_groups(self, lr: float) -> list[dict]:
        return [{"params": list(self.parameters()), "lr": lr, "weight_decay": 0.0}]
