"""``cyclegan``: CycleGAN (Zhu et al. 2017) from RGB to tactile images, the paper's second baseline.

Two ResNet generators (G: RGB -> tactile, F: tactile -> RGB) and two PatchGAN discriminators trained with the
least-squares GAN loss, cycle consistency (lambda 10) and identity (0.5 x lambda) losses and an image pool
of 50 fakes per discriminator. Unpaired: no loss ever compares G(rgb) with the tactile image of the same pair,
so the pairing of the batches is unused.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from tnf.generators.base import Generator, Optimisation
from tnf.generators.nets.gan import PatchDiscriminator, gan_loss, init_weights
from tnf.generators.nets.resnet import ImagePool, ResnetGenerator
from tnf.registry import FROM_YAML, yaml_defaults


class CycleGAN(Generator):
    """CycleGAN baseline: unpaired RGB <-> tactile, ResNet generators, PatchGAN, LSGAN, cycle + identity."""

    optimizer_names = ("g", "d")

    @dataclass
    @yaml_defaults("generator/cyclegan")
    class Config:
        image_size: int = FROM_YAML
        """Input and output image size in pixels (a multiple of 4)."""
        ngf: int = FROM_YAML
        """Channels of the generators' first layer."""
        ndf: int = FROM_YAML
        """Channels of the discriminators' first layer."""
        n_blocks: int = FROM_YAML
        """Residual blocks per generator (the authors: 6 at 128 px, 9 at 256 px)."""
        d_layers: int = FROM_YAML
        """PatchGAN depth (70 x 70 patches)."""
        norm: str = FROM_YAML
        """Normalisation: instance (the authors'), batch or none."""
        lambda_cycle: float = FROM_YAML
        """Weight of each cycle-consistency L1 loss."""
        lambda_identity: float = FROM_YAML
        """Weight of the identity loss, relative to lambda_cycle."""
        pool_size: int = FROM_YAML
        """Generated images kept per discriminator's history pool (0: none)."""
        lr: float = FROM_YAML
        """Adam learning rate."""
        beta1: float = FROM_YAML
        """Adam beta1."""

        def validate(self) -> None:
            if self.image_size % 4:
                raise ValueError(f"image_size must be a multiple of 4, got {self.image_size}")
            if self.norm not in ("batch", "instance", "none"):
                raise ValueError(f"norm must be batch, instance or none, got {self.norm!r}")
            if self.n_blocks < 0 or self.pool_size < 0:
                raise ValueError("n_blocks and pool_size must be >= 0")

    def __init__(self, cfg: Config):
        super().__init__()
        self.cfg = cfg
        self.inputs = ("rgb",)
        self.net_g = ResnetGenerator(3, 3, cfg.ngf, cfg.n_blocks, cfg.norm)  # RGB -> tactile
        self.net_f = ResnetGenerator(3, 3, cfg.ngf, cfg.n_blocks, cfg.norm)  # tactile -> RGB
        self.net_d_tactile = PatchDiscriminator(3, cfg.ndf, cfg.d_layers, cfg.norm)
        self.net_d_rgb = PatchDiscriminator(3, cfg.ndf, cfg.d_layers, cfg.norm)
        for net in (self.net_g, self.net_f, self.net_d_tactile, self.net_d_rgb):
            init_weights(net)
        self.pool_tactile = ImagePool(cfg.pool_size)
        self.pool_rgb = ImagePool(cfg.pool_size)

    def generate(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.check_batch(batch, self.inputs)
        return self.net_g(batch["rgb"])

    def configure_optimizers(self) -> list[torch.optim.Optimizer]:
        betas = (self.cfg.beta1, 0.999)
        fused = next(self.parameters()).is_cuda
        gens = self.trainable(self.net_g, self.net_f)
        discs = self.trainable(self.net_d_tactile, self.net_d_rgb)
        return [
            torch.optim.Adam(gens, lr=self.cfg.lr, betas=betas, fused=fused),
            torch.optim.Adam(discs, lr=self.cfg.lr, betas=betas, fused=fused),
        ]

    def training_step(self, batch: dict[str, torch.Tensor], opt: Optimisation) -> dict[str, torch.Tensor]:
        self.check_batch(batch, ("rgb", "tactile"))
        opt_g, opt_d = opt.optimizers()
        cfg = self.cfg
        rgb, tac = batch["rgb"], batch["tactile"]
        discs = [self.net_d_tactile, self.net_d_rgb]

        # Generators (G and F) with the discriminators frozen.
        for d in discs:
            self.set_requires_grad(d, False)
        fake_tac = self.net_g(rgb)
        rec_rgb = self.net_f(fake_tac)
        fake_rgb = self.net_f(tac)
        rec_tac = self.net_g(fake_rgb)
        loss_idt = torch.zeros((), device=rgb.device)
        if cfg.lambda_identity > 0:
            w = cfg.lambda_cycle * cfg.lambda_identity
            loss_idt = w * (
                F.l1_loss(self.net_g(tac).float(), tac.float()) + F.l1_loss(self.net_f(rgb).float(), rgb.float())
            )
        loss_gan = gan_loss(self.net_d_tactile(fake_tac), True, "lsgan") + gan_loss(
            self.net_d_rgb(fake_rgb), True, "lsgan"
        )
        loss_cycle = cfg.lambda_cycle * (
            F.l1_loss(rec_rgb.float(), rgb.float()) + F.l1_loss(rec_tac.float(), tac.float())
        )
        loss_g = loss_gan + loss_cycle + loss_idt
        opt_g.zero_grad(set_to_none=True)
        opt.backward(loss_g)
        opt_g.step()

        # Discriminators on real images and on pooled earlier fakes.
        for d in discs:
            self.set_requires_grad(d, True)
        pooled_tac = self.pool_tactile.query(fake_tac)
        pooled_rgb = self.pool_rgb.query(fake_rgb)
        logits_real = self.net_d_tactile(tac)
        logits_fake = self.net_d_tactile(pooled_tac)
        loss_d_tac = 0.5 * (gan_loss(logits_real, True, "lsgan") + gan_loss(logits_fake, False, "lsgan"))
        loss_d_rgb = 0.5 * (
            gan_loss(self.net_d_rgb(rgb), True, "lsgan") + gan_loss(self.net_d_rgb(pooled_rgb), False, "lsgan")
        )
        loss_d = loss_d_tac + loss_d_rgb
        opt_d.zero_grad(set_to_none=True)
        opt.backward(loss_d)
        opt_d.step()
        with torch.no_grad():
            loss_l1 = F.l1_loss(fake_tac.float(), tac.float())  # for monitoring only; not optimised
        return {
            "loss_g": loss_g.detach(),
            "loss_g_gan": loss_gan.detach(),
            "loss_cycle": loss_cycle.detach(),
            "loss_idt": loss_idt.detach(),
            "loss_d": loss_d.detach(),
            "loss_l1": loss_l1.detach(),
            # LSGAN outputs: d_real -> 1 and d_fake -> 0 together means the discriminator has won.
            "d_real": logits_real.detach().float().mean(),
            "d_fake": logits_fake.detach().float().mean(),
        }
