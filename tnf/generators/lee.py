"""``lee``: the cGAN of Lee et al. 2019 ("Touching to See and Seeing to Feel"), the paper's first baseline.

A pix2pix-style U-Net from the RGB image alone with 5x5 stride-2 convolutions, batch norm and LeakyReLU in
the encoder, dropout in the first decoder blocks; the discriminator is four 5x5 convolutions and a fully
connected logit on the (RGB, tactile) pair; sigmoid cross-entropy; RMSProp. The L1 weight defaults to 0 as
in the authors' released code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from tnf.generators.base import Generator, Optimisation
from tnf.generators.nets.conditioning import CHANNELS, conditions, needed_keys
from tnf.generators.nets.gan import NoiseDropout, gan_loss, init_weights, norm_layer
from tnf.generators.nets.unet import MultiEncoderUNet
from tnf.registry import FROM_YAML, yaml_defaults


class LeeDiscriminator(nn.Module):
    """Four 5x5 convolutions (64, 128, 256, 512 x ndf/64 channels; strides 2, 2, 2, 1) with batch norm and
    LeakyReLU, then a linear layer: [B, in_ch, S, S] -> one logit per image [B, 1]."""

    def __init__(self, in_ch: int, ndf: int, image_size: int, norm: str = "batch"):
        super().__init__()
        nl = norm_layer(norm)
        chans = [ndf, ndf * 2, ndf * 4, ndf * 8]
        strides = [2, 2, 2, 1]
        layers: list[nn.Module] = []
        cin = in_ch
        for i, (c, s) in enumerate(zip(chans, strides)):
            layers.append(nn.Conv2d(cin, c, 5, s, 2))
            if i > 0:
                layers.append(nl(c))
            layers.append(nn.LeakyReLU(0.2, True))
            cin = c
        self.features = nn.Sequential(*layers)
        side = image_size // 8
        self.fc = nn.Linear(chans[-1] * side * side, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc(self.features(x).flatten(1))


class Lee(Generator):
    """Lee et al. 2019 baseline: RGB-only U-Net cGAN with 5x5 convolutions, FC discriminator, RMSProp."""

    @dataclass
    @yaml_defaults("generator/lee")
    class Config:
        inputs: list[str] = FROM_YAML
        """Conditions (the original uses the RGB image only)."""
        image_size: int = FROM_YAML
        """Input and output image size in pixels (square, a power of two)."""
        ngf: int = FROM_YAML
        """Channels of the first generator layer."""
        ndf: int = FROM_YAML
        """Channels of the first discriminator layer."""
        norm: str = FROM_YAML
        """Normalisation: batch (original), instance or none."""
        dropout: float = FROM_YAML
        """Dropout probability in the first decoder blocks."""
        dropout_blocks: int = FROM_YAML
        """How many of the first decoder blocks have dropout."""
        dropout_at_generation: bool = FROM_YAML
        """Keep dropout on when generating (the original's test mode turns it off)."""
        lambda_l1: float = FROM_YAML
        """Weight of the L1 loss (0 in the authors' released code)."""
        lr: float = FROM_YAML
        """RMSProp learning rate of generator and discriminator."""

        @property
        def num_downs(self) -> int:
            return int(round(math.log2(self.image_size)))

        def validate(self) -> None:
            bad = [k for k in self.inputs if k not in CHANNELS]
            if bad or not self.inputs:
                raise ValueError(f"inputs must be a non-empty subset of {list(CHANNELS)}, got {self.inputs}")
            if self.image_size < 16 or 2**self.num_downs != self.image_size:
                raise ValueError(f"image_size must be a power of two >= 16, got {self.image_size}")
            if self.norm not in ("batch", "instance", "none"):
                raise ValueError(f"norm must be batch, instance or none, got {self.norm!r}")
            if self.lambda_l1 < 0:
                raise ValueError(f"lambda_l1 must be >= 0, got {self.lambda_l1}")

    def __init__(self, cfg: Config):
        super().__init__()
        self.cfg = cfg
        self.inputs = tuple(cfg.inputs)
        # A single-input U-Net: the encoder of the RGB image is also the skip source.
        self.net_g = MultiEncoderUNet(
            cfg.inputs, cfg.inputs, cfg.ngf, cfg.num_downs, cfg.norm, cfg.dropout, cfg.dropout_blocks, kernel=5
        )
        cond_ch = sum(CHANNELS[k] for k in self.inputs)
        self.net_d = LeeDiscriminator(cond_ch + 3, cfg.ndf, cfg.image_size, cfg.norm)
        init_weights(self.net_g)
        init_weights(self.net_d)
        for m in self.net_g.modules():
            if isinstance(m, NoiseDropout):
                m.always_on = cfg.dropout_at_generation

    def generate(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.check_batch(batch, needed_keys(self.inputs))
        return self.net_g(conditions(batch, self.inputs))

    def configure_optimizers(self) -> list[torch.optim.Optimizer]:
        return [
            torch.optim.RMSprop(self.trainable(self.net_g), lr=self.cfg.lr),
            torch.optim.RMSprop(self.trainable(self.net_d), lr=self.cfg.lr),
        ]

    def training_step(self, batch: dict[str, torch.Tensor], opt: Optimisation) -> dict[str, torch.Tensor]:
        self.check_batch(batch, (*needed_keys(self.inputs), "tactile"))
        opt_g, opt_d = opt.optimizers()
        real = batch["tactile"]
        cond = torch.cat(list(conditions(batch, self.inputs).values()), 1)
        fake = self.generate(batch)

        self.set_requires_grad(self.net_d, True)
        logits_fake = self.net_d(torch.cat([cond, fake.detach()], 1))
        logits_real = self.net_d(torch.cat([cond, real], 1))
        loss_d = gan_loss(logits_fake, False, "vanilla") + gan_loss(logits_real, True, "vanilla")
        opt_d.zero_grad(set_to_none=True)
        opt.backward(loss_d)
        opt_d.step()

        self.set_requires_grad(self.net_d, False)
        loss_g_gan = gan_loss(self.net_d(torch.cat([cond, fake], 1)), True, "vanilla")
        loss_l1 = F.l1_loss(fake.float(), real.float())
        loss_g = loss_g_gan + self.cfg.lambda_l1 * loss_l1
        opt_g.zero_grad(set_to_none=True)
        opt.backward(loss_g)
        opt_g.step()
        self.set_requires_grad(self.net_d, True)
        return {
            "loss_g": loss_g.detach(),
            "loss_g_gan": loss_g_gan.detach(),
            "loss_l1": loss_l1.detach(),
            "loss_d": loss_d.detach(),
            "d_real": torch.sigmoid(logits_real.detach().float()).mean(),
            "d_fake": torch.sigmoid(logits_fake.detach().float()).mean(),
        }
