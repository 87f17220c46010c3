"""The one volume renderer shared by every fitted scene kind (``nerf``, ``hashgrid``).

Conventions: cameras are camera-to-world 4x4 matrices in the OpenGL convention (the camera looks along its
-z axis, +y up, image rows go down), metres; intrinsics are ``(fx, fy, cx, cy)`` in pixels and rays go
through pixel centres. Ray directions are unit vectors, so a ray parameter ``t`` is a distance in metres.

A fitted scene implements ``render_rays(origins, dirs, background, perturb)`` for a flat batch of rays;
``FieldScene.render_rgbd`` turns cameras into rays, renders them in chunks and converts the expected
termination distance into z-depth.
"""

from __future__ import annotations

from typing import TypedDict

import torch

from tnf.cameras import camera_rays
from tnf.scenes.base import RGBD, Scene

# Accumulated opacity below which a pixel counts as empty (depth 0).
EMPTY_OPACITY = 1e-4


class RayOutput(TypedDict, total=False):
    """What ``render_rays`` returns for R rays."""

    rgb: torch.Tensor  # [R, 3] in [0, 1], composited over the background
    depth: torch.Tensor  # [R] expected termination distance along the ray (metres), normalised by opacity
    opacity: torch.Tensor  # [R] accumulated opacity in [0, 1]
    rgb_coarse: torch.Tensor  # [R, 3] the coarse network's colour (NeRF only; trained too)
    t_stop: torch.Tensor  # [R] distance after which a marched ray stopped, inf if never (hashgrid, no grad)
    distortion: torch.Tensor  # [R] distortion loss of the weights along each ray (hashgrid, with grad)


def composite(rgba: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """RGB [..., 3] of RGBA [..., 4] over ``background`` ([3] or [..., 3])."""
    a = rgba[..., 3:4]
    return rgba[..., :3] * a + background * (1.0 - a)


def volume_render(
    sigma: torch.Tensor,
    rgb: torch.Tensor,
    t: torch.Tensor,
    delta: torch.Tensor,
    background: torch.Tensor | None = None,
    start: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """The quadrature of the paper's Eq. 1 over N samples on each of R rays.

    ``C = sum_n T_n (1 - exp(-sigma_n delta_n)) c_n + (1 - sum_n w_n) * background`` with
    ``T_n = exp(-sum_{n'<n} sigma_n' delta_n')``.

    Args:
        sigma: [R, N] volume density (1/metre), >= 0.
        rgb: [R, N, 3] colour in [0, 1].
        t: [R, N] sample distances along the ray (metres).
        delta: [R, N] length of each sample's interval (metres); 0 for padding samples.
        background: [3] or [R, 3] colour seen where the ray is not absorbed; None means black.
        start: [R, N] where each sample's interval begins (metres). Given, the depth is the exact expected
            termination distance of the quadrature's model (density constant over each interval); else
            each interval's share is placed at its sample, ``sum_n w_n t_n``, which puts an opaque
            surface up to a whole interval too deep (half of one on average).
    Returns:
        rgb [R, 3], depth [R] (expected termination distance normalised by opacity; 0 where empty),
        opacity [R], weights [R, N].
    """
    tau = sigma * delta
    alpha = 1.0 - torch.exp(-tau)
    # Exclusive cumulative sum: transmittance up to (not including) each sample.
    trans = torch.exp(-(torch.cumsum(tau, dim=-1) - tau))
    weights = alpha * trans
    opacity = weights.sum(-1)
    color = (weights.unsqueeze(-1) * rgb).sum(-2)
    if background is not None:
        color = color + (1.0 - opacity).unsqueeze(-1) * background
    where = t if start is None else start + delta * interval_termination(tau)
    depth = (weights * where).sum(-1) / opacity.clamp_min(1e-10)
    depth = torch.where(opacity > EMPTY_OPACITY, depth, torch.zeros_like(depth))
    return {"rgb": color, "depth": depth, "opacity": opacity, "weights": weights}


def interval_termination(tau: torch.Tensor) -> torch.Tensor:
    """Where light that ends in an interval of constant density ends, as a fraction of the interval's
    length, given its optical thickness ``tau`` (>= 0): ``1/tau - 1/(exp(tau) - 1)``, from 1/2 for a thin
    interval down to 0 for an opaque one (light ends where the interval begins)."""
    small = tau < 1e-2
    safe = torch.where(small, torch.ones_like(tau), tau)
    exact = 1.0 / safe - 1.0 / torch.expm1(safe)
    return torch.where(small, 0.5 - tau / 12.0, exact)


def distortion_loss(weights: torch.Tensor, t: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss per ray, [R] (metres): small when a ray's weights [R, N] gather in
    one short stretch, as on an opaque surface, large when they spread along it.

    ``L = sum_ij w_i w_j |t_i - t_j| + 1/3 sum_i w_i^2 delta_i`` for sample distances t [R, N] in
    increasing order and interval lengths delta [R, N], computed in O(N) with exclusive cumulative sums.
    """
    w_before = torch.cumsum(weights, dim=-1) - weights
    wt_before = torch.cumsum(weights * t, dim=-1) - weights * t
    between = 2.0 * (weights * (t * w_before - wt_before)).sum(-1)
    return between + (weights**2 * delta).sum(-1) / 3.0


def ray_aabb(
    origins: torch.Tensor, dirs: torch.Tensor, lo: torch.Tensor | float, hi: torch.Tensor | float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances [R] of rays (origins [R, 3], dirs [R, 3]) through the axis-aligned box
    ``[lo, hi]`` (corners [3] or scalars, metres); entry is clamped at 0; exit <= entry on a miss."""
    safe = torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    inv = 1.0 / safe
    t0 = (lo - origins) * inv
    t1 = (hi - origins) * inv
    near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    far = torch.maximum(t0, t1).amin(-1)
    return near, far


def ray_box(origins: torch.Tensor, dirs: torch.Tensor, bound: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances [R] of rays through the cube [-bound, bound]^3; exit <= entry on a miss."""
    return ray_aabb(origins, dirs, -bound, bound)


class FieldScene(Scene):
    """A scene rendered by volume rendering of a learned field inside the cube [-bound, bound]^3.

    Subclasses implement ``render_rays``; this class renders whole cameras in chunks of rays.
    Buffers: ``background`` [3], the colour composited behind the object.
    """

    background: torch.Tensor

    def __init__(self, bound: float, background: tuple[float, float, float]):
        super().__init__()
        self.bound = float(bound)
        self.register_buffer("background", torch.tensor(background, dtype=torch.float32))

    def render_rays(
        self,
        origins: torch.Tensor,
        dirs: torch.Tensor,
        background: torch.Tensor | None = None,
        perturb: bool = False,
    ) -> RayOutput:
        """Render R rays: origins [R, 3], unit dirs [R, 3]; background [3] or [R, 3] (default the scene's)."""
        raise NotImplementedError

    def update_occupancy(self, step: int) -> None:
        """Called once per training step before rendering; scenes with an occupancy grid refresh it here."""

    default_chunk: int = 1 << 15

    @torch.no_grad()
    def render_rgbd(
        self,
        c2w: torch.Tensor,
        intrinsics: torch.Tensor,
        width: int,
        height: int,
        chunk: int | None = None,
    ) -> RGBD:
        """Render B views: c2w [B, 4, 4] (or [4, 4]), intrinsics [B, 4] or [4]; ``chunk`` rays per batch."""
        # Inference mode rather than no_grad saves bookkeeping on each of the many small operations of a
        # ray march; the results are copied out of it, since inference tensors cannot enter autograd later.
        with torch.inference_mode():
            out = self._render_views(c2w, intrinsics, width, height, chunk)
        return {"rgb": out["rgb"].clone(), "depth": out["depth"].clone(), "opacity": out["opacity"].clone()}

    def _render_views(self, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int, chunk: int | None):
        dev = self.background.device
        c2w = c2w.to(dev)
        origins, dirs, z_scale = camera_rays(c2w, intrinsics.to(dev), width, height)
        B = origins.shape[0]
        o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
        chunk = chunk or self.default_chunk
        rgb, depth, opacity = [], [], []
        for i in range(0, o.shape[0], chunk):
            out = self.render_rays(o[i : i + chunk], d[i : i + chunk])
            rgb.append(out["rgb"])
            depth.append(out["depth"])
            opacity.append(out["opacity"])
        shape = (B, height, width)
        return {
            "rgb": torch.cat(rgb).reshape(*shape, 3).clamp(0, 1),
            "depth": torch.cat(depth).reshape(shape) * z_scale,
            "opacity": torch.cat(opacity).reshape(shape).clamp(0, 1),
        }
