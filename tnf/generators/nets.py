"""Network building blocks shared by the generators: norms, noise dropout, PatchGAN, ResNet blocks, image pool.

All images are [B, C, H, W] float tensors in [-1, 1].
"""

from __future__ import annotations

import functools
import random
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn


def norm_layer(kind: str) -> Callable[[int], nn.Module]:
    """``batch`` | ``instance`` | ``none`` -> a constructor ``f(channels) -> nn.Module``."""
    if kind == "batch":
        return functools.partial(nn.BatchNorm2d, affine=True, track_running_stats=True)
    if kind == "instance":
        return functools.partial(nn.InstanceNorm2d, affine=False, track_running_stats=False)
    if kind == "none":
        return lambda c: nn.Identity()
    raise ValueError(f"norm must be batch, instance or none, got {kind!r}")


class NoiseDropout(nn.Module):
    """Dropout that can stay active in eval mode: the cGAN's noise z (pix2pix) is dropout at test time too.

    ``always_on`` is set by the generator from its config; batch-norm layers still use running statistics
    in eval mode.
    """

    def __init__(self, p: float = 0.5):
        super().__init__()
        self.p = p
        self.always_on = False

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.p <= 0:
            return x
        return F.dropout(x, self.p, training=self.training or self.always_on)

    def extra_repr(self) -> str:
        return f"p={self.p}, always_on={self.always_on}"


def init_weights(net: nn.Module, gain: float = 0.02) -> None:
    """pix2pix/DCGAN initialisation: conv weights N(0, gain), norm weights N(1, gain), biases 0."""
    for m in net.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
            nn.init.normal_(m.weight, 0.0, gain)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.normal_(m.weight, 1.0, gain)
            nn.init.zeros_(m.bias)


class PatchDiscriminator(nn.Module):
    """PatchGAN discriminator (pix2pix, CycleGAN): [B, in_ch, H, W] -> logits [B, 1, H/8 - 2, W/8 - 2].

    With ``n_layers=3`` each output logit sees a 70 x 70 pixel patch (14 x 14 logits for a 128 x 128 input).
    """

    def __init__(self, in_ch: int, ndf: int = 64, n_layers: int = 3, norm: str = "batch"):
        super().__init__()
        nl = norm_layer(norm)
        use_bias = norm != "batch"
        layers: list[nn.Module] = [nn.Conv2d(in_ch, ndf, 4, 2, 1), nn.LeakyReLU(0.2, True)]
        mult = 1
        for n in range(1, n_layers + 1):
            prev, mult = mult, min(2**n, 8)
            stride = 2 if n < n_layers else 1
            layers += [
                nn.Conv2d(ndf * prev, ndf * mult, 4, stride, 1, bias=use_bias),
                nl(ndf * mult),
                nn.LeakyReLU(0.2, True),
            ]
        layers.append(nn.Conv2d(ndf * mult, 1, 4, 1, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class ResnetBlock(nn.Module):
    """Residual block of two 3x3 convolutions with reflection padding (CycleGAN's generator)."""

    def __init__(self, ch: int, norm: str = "instance", dropout: float = 0.0):
        super().__init__()
        nl = norm_layer(norm)
        use_bias = norm != "batch"
        layers: list[nn.Module] = [nn.ReflectionPad2d(1), nn.Conv2d(ch, ch, 3, bias=use_bias), nl(ch), nn.ReLU(True)]
        if dropout > 0:
            layers.append(nn.Dropout(dropout))
        layers += [nn.ReflectionPad2d(1), nn.Conv2d(ch, ch, 3, bias=use_bias), nl(ch)]
        self.block = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.block(x)


class ResnetGenerator(nn.Module):
    """CycleGAN's ResNet generator: c7s1-ngf, two stride-2 downs, ``n_blocks`` residual blocks, two ups,
    c7s1-out, tanh. [B, in_ch, H, W] -> [B, out_ch, H, W] in [-1, 1] (H, W multiples of 4)."""

    def __init__(self, in_ch: int, out_ch: int, ngf: int = 64, n_blocks: int = 6, norm: str = "instance"):
        super().__init__()
        nl = norm_layer(norm)
        use_bias = norm != "batch"
        layers: list[nn.Module] = [
            nn.ReflectionPad2d(3),
            nn.Conv2d(in_ch, ngf, 7, bias=use_bias),
            nl(ngf),
            nn.ReLU(True),
        ]
        ch = ngf
        for _ in range(2):
            layers += [nn.Conv2d(ch, ch * 2, 3, 2, 1, bias=use_bias), nl(ch * 2), nn.ReLU(True)]
            ch *= 2
        layers += [ResnetBlock(ch, norm) for _ in range(n_blocks)]
        for _ in range(2):
            layers += [
                nn.ConvTranspose2d(ch, ch // 2, 3, 2, 1, output_padding=1, bias=use_bias),
                nl(ch // 2),
                nn.ReLU(True),
            ]
            ch //= 2
        layers += [nn.ReflectionPad2d(3), nn.Conv2d(ch, out_ch, 7), nn.Tanh()]
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class ImagePool:
    """A history of generated images (Shrivastava et al.): the discriminator sees a mix of current and older
    fakes, which damps oscillation. ``size=0`` returns the input unchanged.

    While the pool fills, each image enters it and is returned; then each image is, with probability 1/2, swapped
    with a random stored one (the stored one is returned) or returned as it is. The draws are made image by image
    from Python's ``random``; the images move in one gather and one scatter per batch, not one copy each.
    """

    def __init__(self, size: int = 50):
        self.size = size
        self.images: torch.Tensor | None = None  # [filled, C, H, W], the stored images
        self.filled = 0

    def query(self, images: torch.Tensor) -> torch.Tensor:
        """The images ``[B, C, H, W]`` the discriminator sees in place of ``images`` (detached)."""
        if self.size == 0:
            return images
        images = images.detach()
        n = images.shape[0]
        if self.images is None or self.images.shape[1:] != images.shape[1:]:
            self.images = images.new_empty((self.size, *images.shape[1:]))
            self.filled = 0
        elif self.images.dtype != images.dtype or self.images.device != images.device:
            self.images = self.images.to(images)
        # Decide every image's fate first. source[j]: index into cat(stored, batch) of what image j returns;
        # slot_from[i]: the batch image that slot i holds after this batch.
        source: list[int] = []
        slot_from: dict[int, int] = {}
        for j in range(n):
            if self.filled < self.size:
                slot_from[self.filled] = j
                self.filled += 1
                source.append(self.size + j)
            elif random.random() > 0.5:
                i = random.randrange(self.size)
                source.append(self.size + slot_from[i] if i in slot_from else i)
                slot_from[i] = j
            else:
                source.append(self.size + j)
        index = torch.tensor(source, device=images.device)
        out = torch.cat([self.images, images], 0).index_select(0, index)
        if slot_from:
            slots = torch.tensor(list(slot_from), device=images.device)
            self.images.index_copy_(
                0, slots, images.index_select(0, torch.tensor(list(slot_from.values()), device=images.device))
            )
        return out


def set_requires_grad(nets: nn.Module | list[nn.Module], flag: bool) -> None:
    """Freeze or unfreeze every parameter of ``nets`` (the discriminator while the generator steps)."""
    for net in nets if isinstance(nets, list) else [nets]:
        for p in net.parameters():
            p.requires_grad_(flag)
