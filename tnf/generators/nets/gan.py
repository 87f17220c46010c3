"""Network parts that every GAN here shares: norms, noise dropout, pix2pix initialisation, the PatchGAN
discriminator and the GAN losses.

All images are [B, C, H, W] float tensors in [-1, 1].
"""

from __future__ import annotations

import functools
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


def set_requires_grad(nets: nn.Module | list[nn.Module], flag: bool) -> None:
    """Freeze or unfreeze every parameter of ``nets`` (the discriminator while the generator steps)."""
    for net in nets if isinstance(nets, list) else [nets]:
        for p in net.parameters():
            p.requires_grad_(flag)


def gan_loss(logits: torch.Tensor, real: bool, mode: str) -> torch.Tensor:
    """GAN loss of discriminator ``logits`` against the label real/fake: ``vanilla`` (sigmoid cross-entropy)
    or ``lsgan`` (least squares)."""
    target = torch.ones_like(logits) if real else torch.zeros_like(logits)
    if mode == "lsgan":
        return F.mse_loss(logits.float(), target.float())
    return F.binary_cross_entropy_with_logits(logits.float(), target.float())


def d_output(logits: torch.Tensor, mode: str) -> torch.Tensor:
    """The discriminator's mean output on the scale its loss targets (1 = real, 0 = generated): the sigmoid of
    the logits for ``vanilla``, the logits themselves for ``lsgan`` (which regresses them to 1 and 0)."""
    x = logits.detach().float()
    return (torch.sigmoid(x) if mode == "vanilla" else x).mean()
