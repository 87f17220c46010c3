"""What a generator is conditioned on: the condition images made from a batch (``conditions``: the depth
image's slopes, the learned surface field's features), the pixels' positions, and the touch's force (an input
plane, or FiLM of the features).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from tnf.errors import TnfError
from tnf.generators.field import SurfaceField

CHANNELS = {"rgb": 3, "depth": 1, "background": 3, "depth_slope": 2, "depth_and_slope": 3, "prior": 3, "surface": 0}
"""Channels of each condition a generator may take. ``depth_slope`` and ``depth_and_slope`` (the depth image
with its slopes, for one encoder to see both) are derived from ``depth`` (``conditions``); ``prior``, the
simulator's image of the depth crop (``tnf.data.prior``), comes with datasets made with ``pair.prior=true``;
``surface``, the features of a learned field over the trained objects' surfaces (``tnf.generators.field``), is
looked up at the surface points of datasets made with ``pair.points=true`` (its channels: the field's)."""

SLOPE_GAIN = 64.0
"""``depth_slope`` = this times the depth image's change per pixel, clipped to [-1, 1]. At sim_digit's framing
(a 40 mm depth window over a crop of about 30 mm) a 45 degree slope is about 0.75, so the gel-sized relief that
an imprint shows spans the range, and the crop's edges (jumps to the far plane) clip."""


def _slopes(depth: torch.Tensor, with_depth: bool) -> torch.Tensor:
    """The x and y slopes of ``depth`` [B, 1, H, W] (after the depth image itself when ``with_depth``), in one
    new buffer: central differences, one-sided at the edges (the replicated edge's central difference), times
    ``SLOPE_GAIN``, clipped to [-1, 1]. Written into the buffer rather than padded, differenced and concatenated:
    at a generation batch of 1,024 images the intermediate tensors are most of the derivation's memory traffic.
    Assignments into the buffer's views (not ``out=`` arguments) keep it differentiable in ``depth``."""
    if depth.dim() != 4 or depth.shape[1] != 1 or min(depth.shape[-2:]) < 2:
        raise TnfError(f"depth slopes need a depth image batch [B, 1, H, W] with H, W >= 2, got {tuple(depth.shape)}")
    b, _, h, w = depth.shape
    out = depth.new_empty(b, 2 + with_depth, h, w)
    if with_depth:
        out[:, :1] = depth
    dx, dy = out[:, -2:-1], out[:, -1:]
    dx[..., 1:-1] = depth[..., 2:] - depth[..., :-2]
    dx[..., :1] = depth[..., 1:2] - depth[..., :1]
    dx[..., -1:] = depth[..., -1:] - depth[..., -2:-1]
    dy[..., 1:-1, :] = depth[..., 2:, :] - depth[..., :-2, :]
    dy[..., :1, :] = depth[..., 1:2, :] - depth[..., :1, :]
    dy[..., -1:, :] = depth[..., -1:, :] - depth[..., -2:-1, :]
    out[:, -2:].mul_(SLOPE_GAIN / 2).clamp_(-1.0, 1.0)  # a power-of-two scale: exactly (difference / 2) * gain
    return out


def depth_slope(depth: torch.Tensor) -> torch.Tensor:
    """[B, 2, H, W] x and y slopes of a depth image [B, 1, H, W] (central differences, edges replicated), times
    ``SLOPE_GAIN``, clipped to [-1, 1]: the surface's orientation, which is what a lit gel's image shows."""
    return _slopes(depth, with_depth=False)


def depth_and_slope(depth: torch.Tensor) -> torch.Tensor:
    """[B, 3, H, W]: the depth image [B, 1, H, W] and its ``depth_slope``, for one encoder to see both."""
    return _slopes(depth, with_depth=True)


DERIVED: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "depth_slope": depth_slope,
    "depth_and_slope": depth_and_slope,
}
"""The conditions made from the depth image, and how."""


def needed_keys(inputs: tuple[str, ...]) -> tuple[str, ...]:
    """The batch keys that ``inputs`` are made from (the derived ones from ``depth``, ``surface`` from the surface
    points and the object)."""
    keys: list[str] = []
    for k in inputs:
        keys += ["depth"] if k in DERIVED else ["points", "object_id"] if k == "surface" else [k]
    return tuple(dict.fromkeys(keys))


def conditions(
    batch: dict[str, torch.Tensor], inputs: tuple[str, ...], field: SurfaceField | None = None
) -> dict[str, torch.Tensor]:
    """The condition images named in ``inputs``, from a batch (derived ones computed from theirs; ``surface``
    looked up in ``field``)."""
    out = {}
    for k in inputs:
        if k == "surface":
            if field is None:
                raise TnfError("the surface input needs the generator's surface field")
            out[k] = field(batch["points"], batch["object_id"]).to(batch["depth"].dtype)
        else:
            out[k] = DERIVED[k](batch["depth"]) if k in DERIVED else batch[k]
    return out


def coordinate_grid(size: int) -> torch.Tensor:
    """[1, 2, size, size]: each pixel centre's x (along the width) and y (down the rows), from -1 + 1/size to
    1 - 1/size. Appended to an input (``coords``), they tell the convolutions where in the gel a pixel lies: the
    gel's sag and the lights' directions, which an imprint's shading follows, depend on it, and a convolution
    alone cannot tell one place from another."""
    c = (torch.arange(size, dtype=torch.float32) * 2 + 1) / size - 1
    y, x = torch.meshgrid(c, c, indexing="ij")
    return torch.stack([x, y])[None]


FORCE_MODES = ("none", "film", "plane")
"""How a generator sees the touch's force: not at all, FiLM (a scale and shift of the bottleneck and every decoder
block's features, from a small network of the force) or a constant input plane appended to every input."""


def force_input(force: torch.Tensor, center: float, scale: float) -> torch.Tensor:
    """[B] forces in newtons -> [B] float32 ``(force - center) / scale`` (the training range maps to [-1, 1])."""
    return (force.float() - center) / scale


def force_plane(force: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """[B, 1, H, W] planes holding each image's normalised force, in ``like``'s dtype and size."""
    b, _, h, w = like.shape
    return force.to(like.dtype).view(b, 1, 1, 1).expand(b, 1, h, w)


class _Film:
    """Per-layer (scale, shift) pairs of one batch: ``film(i, x)`` = ``x * (1 + scale_i) + shift_i``."""

    def __init__(self, params: list[tuple[torch.Tensor, torch.Tensor]]):
        self.params = params

    def __call__(self, i: int, x: torch.Tensor) -> torch.Tensor:
        g, b = self.params[i]
        return x * (1 + g.to(x.dtype)[..., None, None]) + b.to(x.dtype)[..., None, None]


class ForceFiLM(nn.Module):
    """FiLM (Perez et al. 2018) from the force: a two-layer network maps the [B] normalised force to a scale and
    a shift per channel of each layer in ``channels``. Its last layer starts at zero, so an untrained FiLM leaves
    every feature as it is."""

    def __init__(self, channels: list[int], hidden: int = 64):
        super().__init__()
        self.channels = list(channels)
        self.net = nn.Sequential(nn.Linear(1, hidden), nn.ReLU(True), nn.Linear(hidden, 2 * sum(self.channels)))

    def reset(self) -> None:
        """PyTorch's default initialisation for the first layer (the GAN's N(0, 0.02) would leave its features
        near zero, and the force with them) and zeros for the last: FiLM starts as the identity."""
        first, last = self.net[0], self.net[-1]
        assert isinstance(first, nn.Linear) and isinstance(last, nn.Linear)
        first.reset_parameters()
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, force: torch.Tensor) -> _Film:
        y = self.net(force.float().view(-1, 1))
        params, at = [], 0
        for c in self.channels:
            params.append((y[:, at : at + c], y[:, at + c : at + 2 * c]))
            at += 2 * c
        return _Film(params)
