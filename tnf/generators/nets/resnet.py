"""CycleGAN's networks: the ResNet generator and the pool of generated images its discriminators see.

All images are [B, C, H, W] float tensors in [-1, 1].
"""

from __future__ import annotations

import random

import torch
from torch import nn

from tnf.generators.nets.gan import norm_layer


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
