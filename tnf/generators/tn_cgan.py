"""``tn_cgan``: the Touch-NeRF conditional GAN (the paper's Fig. 2).

The RGB image, the depth image (by default with its slopes) and the sensor's background image go through
separate convolutional encoders; their innermost features are concatenated and decoded by a U-Net decoder into
the tactile image, with skip connections from the background and depth encoders (configurable) at every
scale. A PatchGAN discriminator judges (condition, tactile) pairs; the generator minimises the cGAN loss plus
lambda_L1 times the L1 distance to the real image, plus lambda_SSIM times (1 - SSIM).

The defaults depart from the paper's figure in seven settings (depth skips, no dropout, a full-resolution head,
an SSIM term, a residual output, no adversarial term, depth with its slopes); the paper's layout is
``inputs=[rgb,depth,background] skips=[background] dropout=0.5 lambda_ssim=0 full_res_head=false residual=false
lambda_gan=1``. Why: docs/decisions/tn_cgan_defaults.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

from tnf import metrics
from tnf.generators.base import Generator, Optimisation
from tnf.generators.field import SurfaceField
from tnf.generators.nets.conditioning import CHANNELS, FORCE_MODES, conditions, force_input, force_plane, needed_keys
from tnf.generators.nets.gan import NoiseDropout, PatchDiscriminator, d_output, gan_loss, init_weights
from tnf.generators.nets.unet import MultiEncoderUNet
from tnf.registry import FROM_YAML, yaml_defaults

PRESS_LEVELS = 10
"""A pixel is part of the press where the real image differs from the background by more than this (of 255)."""


def press_mask(real: torch.Tensor, background: torch.Tensor, margin: int) -> torch.Tensor:
    """1 where ``real`` differs from ``background`` (both ``[B, 3, H, W]`` in [-1, 1]) by more than
    ``PRESS_LEVELS`` of 255 in any channel, grown by ``margin`` pixels; 0 elsewhere. ``[B, 1, H, W]``."""
    diff = (real.float() - background.float()).abs().amax(1, keepdim=True) > 2 * PRESS_LEVELS / 255
    mask = diff.float()
    if margin > 0:
        mask = F.max_pool2d(mask, 2 * margin + 1, stride=1, padding=margin)
    return mask


def press_only(fake: torch.Tensor, real: torch.Tensor, background: torch.Tensor, margin: int) -> torch.Tensor:
    """``fake`` with its gradient kept only inside the press (``press_mask``): the same values, so the
    discriminator sees the whole image, but what it asks of the generator changes only the pressed pixels."""
    mask = press_mask(real, background, margin).to(fake.dtype)
    return fake * mask + fake.detach() * (1 - mask)


class TNcGAN(Generator):
    """Touch-NeRF cGAN: separate RGB / depth / background encoders, U-Net decoder, PatchGAN, cGAN + L1 + SSIM loss."""

    @dataclass
    @yaml_defaults("generator/tn_cgan")
    class Config:
        inputs: list[str] = FROM_YAML
        """Conditions, each with its own encoder: any of rgb, depth, background (drop some for ablations),
        depth_slope, the depth image's x and y slopes (``depth_slope``), which a lit gel's image follows, and
        depth_and_slope, the two together for one encoder (the default, in place of the paper's depth); prior,
        the simulator's image of the depth crop (datasets made with ``pair.prior=true``), and surface, the
        features of a surface field learned with the generator (datasets made with ``pair.points=true``)."""
        skips: list[str] = FROM_YAML
        """Inputs whose encoder features are skip-connected to the decoder (the paper: background only). Depth
        skips place the imprint's edges from the depth image at every scale, not from the 1 x 1 bottleneck."""
        image_size: int = FROM_YAML
        """Input and output image size in pixels (square, a power of two)."""
        ngf: int = FROM_YAML
        """Channels of the first encoder/last decoder layer (doubling per level up to 8 x ngf)."""
        ndf: int = FROM_YAML
        """Channels of the discriminator's first layer."""
        d_layers: int = FROM_YAML
        """PatchGAN depth: 3 gives 70 x 70 pixel patches."""
        norm: str = FROM_YAML
        """Normalisation in generator and discriminator: batch, instance or none."""
        dropout: float = FROM_YAML
        """Dropout probability in the innermost decoder blocks (the noise z; pix2pix and the paper: 0.5)."""
        dropout_blocks: int = FROM_YAML
        """How many innermost decoder blocks have dropout (pix2pix: 3)."""
        dropout_at_generation: bool = FROM_YAML
        """Keep dropout on when generating (the noise z), as pix2pix; false for deterministic outputs."""
        gan_mode: str = FROM_YAML
        """Adversarial loss: vanilla (sigmoid cross-entropy, the paper's Eq. 3) or lsgan."""
        lambda_gan: float = FROM_YAML
        """Weight of the adversarial term in the generator's loss (the paper: 1). 0, the default, trains the
        generator as a plain regression on the L1 and SSIM terms: the discriminator then has no optimiser and is
        never run."""
        gan_press_margin: int = FROM_YAML
        """Where the adversarial term shapes the image. -1: every pixel (the paper). k >= 0: only pixels within k
        pixels of the press, where the real image differs from the background by more than ``PRESS_LEVELS`` of 255
        in any channel; elsewhere only the L1 and SSIM terms reach the generator."""
        lambda_l1: float = FROM_YAML
        """Weight lambda of the L1 loss (Eq. 2)."""
        lambda_ssim: float = FROM_YAML
        """Weight of an SSIM loss, 1 - SSIM (the evaluation's window and constants), added to the generator's
        loss (0: the paper's cGAN + L1 loss only)."""
        full_res_head: bool = FROM_YAML
        """End the decoder in two 3 x 3 convolutions at full resolution that also see the skip inputs' own
        images (the 128 px depth, say); false: the decoder's last transposed convolution makes the image."""
        residual: bool = FROM_YAML
        """Add the network's output to an input image (``residual_on``) instead of making the image outright:
        only the change that the press makes (or what the prior gets wrong) is learned."""
        residual_on: str = FROM_YAML
        """The input image the residual output adds to: background, or prior (the simulator's image of the depth
        crop, ``pair.prior=true``). It must be in inputs."""
        coords: list[str] = FROM_YAML
        """Inputs that also get each pixel's x and y position as two channels (``coordinate_grid``), for their
        encoder and, if skipped, the head: where on the gel a pixel lies changes how a press there looks (the
        gel's sag, the lights' directions). Empty: the network sees positions only through its borders."""
        force: str = FROM_YAML
        """How the generator sees each touch's force (datasets made with ``pair.force=true``; docs/force.md):
        none, film (FiLM on the bottleneck and the decoder's features) or plane (a constant input plane)."""
        force_center: float = FROM_YAML
        """With a force: the force (newtons) that maps to 0; the training range's middle."""
        force_scale: float = FROM_YAML
        """With a force: the force span (newtons) that maps to 1; the training range's half width."""
        surface_levels: int = FROM_YAML
        """With ``surface`` in inputs: the surface field's grid levels (``tnf.generators.field``)."""
        surface_features: int = FROM_YAML
        """With ``surface``: features per grid vertex and level (the input has levels x features channels)."""
        surface_coarsest: float = FROM_YAML
        """With ``surface``: the coarsest grid cell, metres."""
        surface_finest: float = FROM_YAML
        """With ``surface``: the finest grid cell, metres."""
        surface_log2_table: int = FROM_YAML
        """With ``surface``: hash table entries per level, as a power of two."""
        surface_dropout: float = FROM_YAML
        """With ``surface``: the share of training pairs whose field features are zeroed, so that the generator
        also works for objects the field never saw."""
        surface_lr: float = FROM_YAML
        """With ``surface``: Adam learning rate of the field's table (hash grids learn at far larger rates than
        convolutions)."""
        lr: float = FROM_YAML
        """Adam learning rate of generator and discriminator."""
        beta1: float = FROM_YAML
        """Adam beta1."""
        beta2: float = FROM_YAML
        """Adam beta2."""

        @property
        def num_downs(self) -> int:
            return int(round(math.log2(self.image_size)))

        def validate(self) -> None:
            bad = [k for k in self.inputs if k not in CHANNELS]
            if bad or not self.inputs:
                raise ValueError(f"inputs must be a non-empty subset of {list(CHANNELS)}, got {self.inputs}")
            if len(set(self.inputs)) != len(self.inputs):
                raise ValueError(f"inputs has duplicates: {self.inputs}")
            stray = [k for k in self.coords if k not in self.inputs]
            if stray:
                raise ValueError(f"coords {stray} are not in inputs {self.inputs}; set coords to a subset of inputs")
            extra = [k for k in self.skips if k not in self.inputs]
            if extra:
                raise ValueError(f"skips {extra} are not in inputs {self.inputs}; set skips to a subset of inputs")
            if self.image_size < 16 or 2**self.num_downs != self.image_size:
                raise ValueError(f"image_size must be a power of two >= 16, got {self.image_size}")
            if self.image_size < 2 ** (self.d_layers + 2):
                raise ValueError(f"image_size {self.image_size} is too small for d_layers={self.d_layers}")
            if self.norm not in ("batch", "instance", "none"):
                raise ValueError(f"norm must be batch, instance or none, got {self.norm!r}")
            if self.gan_mode not in ("vanilla", "lsgan"):
                raise ValueError(f"gan_mode must be vanilla or lsgan, got {self.gan_mode!r}")
            if not 0 <= self.dropout < 1:
                raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
            if min(self.lambda_gan, self.lambda_l1, self.lambda_ssim) < 0:
                raise ValueError(
                    f"loss weights must be >= 0, got lambda_gan={self.lambda_gan}, lambda_l1={self.lambda_l1}, "
                    f"lambda_ssim={self.lambda_ssim}"
                )
            if self.gan_press_margin < -1:
                raise ValueError(f"gan_press_margin must be -1 (every pixel) or >= 0, got {self.gan_press_margin}")
            if self.gan_press_margin >= 0 and "background" not in self.inputs:
                raise ValueError("gan_press_margin finds the press against the background: add background to inputs")
            if self.gan_press_margin >= 0 and self.lambda_gan == 0:
                raise ValueError(
                    f"gan_press_margin={self.gan_press_margin} limits the adversarial term, which lambda_gan=0 turns "
                    "off: set lambda_gan > 0, or gan_press_margin=-1"
                )
            if self.lambda_gan == self.lambda_l1 == self.lambda_ssim == 0:
                raise ValueError("lambda_gan, lambda_l1 and lambda_ssim are all 0: the generator has no loss")
            if self.residual_on not in ("background", "prior"):
                raise ValueError(f"residual_on must be background or prior, got {self.residual_on!r}")
            if self.residual and self.residual_on not in self.inputs:
                raise ValueError(
                    f"residual adds to the {self.residual_on} image: inputs {self.inputs} must include "
                    f"{self.residual_on} (or set generator.residual=false)"
                )
            if self.force not in FORCE_MODES:
                raise ValueError(f"force must be one of {', '.join(FORCE_MODES)}, got {self.force!r}")
            if not (math.isfinite(self.force_center) and math.isfinite(self.force_scale) and self.force_scale > 0):
                raise ValueError(
                    f"force_center must be finite and force_scale > 0, got {self.force_center}, {self.force_scale}"
                )
            if self.ngf < 1 or self.ndf < 1:
                raise ValueError(f"ngf and ndf must be >= 1, got {self.ngf}, {self.ndf}")

    def __init__(self, cfg: Config):
        super().__init__()
        self.cfg = cfg
        self.inputs = tuple(cfg.inputs)
        self.field: SurfaceField | None = None
        if "surface" in self.inputs:
            self.field = SurfaceField(
                cfg.surface_levels,
                cfg.surface_features,
                cfg.surface_coarsest,
                cfg.surface_finest,
                cfg.surface_log2_table,
                dropout=cfg.surface_dropout,
            )
        channels = {"surface": self.field.channels if self.field is not None else 0}
        self.net_g = MultiEncoderUNet(
            cfg.inputs,
            cfg.skips,
            cfg.ngf,
            cfg.num_downs,
            cfg.norm,
            cfg.dropout,
            cfg.dropout_blocks,
            full_res_head=cfg.full_res_head,
            residual=cfg.residual,
            coords=cfg.coords,
            residual_on=cfg.residual_on,
            channels=channels,
            force=cfg.force,
        )
        cond_ch = sum({**CHANNELS, **channels}[k] for k in self.inputs) + (cfg.force != "none")
        self.net_d = PatchDiscriminator(cond_ch + 3, cfg.ndf, cfg.d_layers, cfg.norm)
        init_weights(self.net_g)
        init_weights(self.net_d)
        if self.net_g.film is not None:
            self.net_g.film.reset()
        for m in self.net_g.modules():
            if isinstance(m, NoiseDropout):
                m.always_on = cfg.dropout_at_generation

    @property
    def uses_force(self) -> bool:
        """Whether the generator is conditioned on the touch's force (batch key ``force``, newtons)."""
        return self.cfg.force != "none"

    def _force(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        if not self.uses_force:
            return None
        return force_input(batch["force"], self.cfg.force_center, self.cfg.force_scale)

    def _keys(self) -> tuple[str, ...]:
        return (*needed_keys(self.inputs), *(("force",) if self.uses_force else ()))

    def condition(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        cond = list(conditions(batch, self.inputs, self.field).values())
        f = self._force(batch)
        if f is not None:  # the discriminator judges the press at its force
            cond.append(force_plane(f, cond[0]))
        return torch.cat(cond, 1)

    def generate(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        self.check_batch(batch, self._keys())
        return self.net_g(conditions(batch, self.inputs, self.field), self._force(batch))

    def fixed_graph(self) -> bool:
        return self.cfg.lambda_gan == 0  # a regression: one backward through the generator every step

    def configure_optimizers(self) -> list[torch.optim.Optimizer]:
        betas = (self.cfg.beta1, self.cfg.beta2)
        fused = next(self.parameters()).is_cuda  # one kernel per step instead of several per tensor
        groups: list[dict[str, Any]] = [{"params": self.trainable(self.net_g)}]
        field = self.trainable(self.field) if self.field is not None else []
        if field:  # (a frozen field has nothing to train)
            groups.append({"params": field, "lr": self.cfg.surface_lr})
        opts: list[torch.optim.Optimizer] = [torch.optim.Adam(groups, lr=self.cfg.lr, betas=betas, fused=fused)]
        if self.cfg.lambda_gan > 0:  # no game, no D optimiser
            opts.append(torch.optim.Adam(self.trainable(self.net_d), lr=self.cfg.lr, betas=betas, fused=fused))
        return opts

    def training_step(self, batch: dict[str, torch.Tensor], opt: Optimisation) -> dict[str, torch.Tensor]:
        self.check_batch(batch, (*self._keys(), "tactile"))
        opts = opt.optimizers()  # [generator's, discriminator's] ([generator's] without the adversarial term)
        opt_g = opts[0]
        real = batch["tactile"]
        fake = self.generate(batch)
        losses: dict[str, torch.Tensor] = {}

        adversarial = self.cfg.lambda_gan > 0
        loss_g = fake.new_zeros((), dtype=torch.float32)
        if adversarial:
            # Discriminator: real pairs -> 1, generated pairs -> 0.
            cond = self.condition(batch)
            self.set_requires_grad(self.net_d, True)
            logits_fake = self.net_d(torch.cat([cond, fake.detach()], 1))
            logits_real = self.net_d(torch.cat([cond, real], 1))
            loss_d = 0.5 * (
                gan_loss(logits_fake, False, self.cfg.gan_mode) + gan_loss(logits_real, True, self.cfg.gan_mode)
            )
            opts[1].zero_grad(set_to_none=True)
            opt.backward(loss_d)
            opts[1].step()
            # Generator: fool the (frozen) discriminator.
            self.set_requires_grad(self.net_d, False)
            shaped = fake
            if self.cfg.gan_press_margin >= 0:
                shaped = press_only(fake, real, batch["background"], self.cfg.gan_press_margin)
            loss_g_gan = gan_loss(self.net_d(torch.cat([cond, shaped], 1)), True, self.cfg.gan_mode)
            loss_g = loss_g + self.cfg.lambda_gan * loss_g_gan
            losses |= {
                "loss_g_gan": loss_g_gan.detach(),
                "loss_d": loss_d.detach(),
                # Mean D outputs: d_real -> 1 and d_fake -> 0 together means the discriminator has won.
                "d_real": d_output(logits_real, self.cfg.gan_mode),
                "d_fake": d_output(logits_fake, self.cfg.gan_mode),
            }

        # ... and stay close to the real image.
        loss_l1 = F.l1_loss(fake.float(), real.float())
        loss_g = loss_g + self.cfg.lambda_l1 * loss_l1
        if self.cfg.lambda_ssim > 0:
            loss_ssim = 1 - metrics.ssim_unquantised(fake, real).mean()
            loss_g = loss_g + self.cfg.lambda_ssim * loss_ssim
            losses["loss_ssim"] = loss_ssim.detach()
        opt_g.zero_grad(set_to_none=True)
        opt.backward(loss_g)
        opt_g.step()
        if adversarial:
            self.set_requires_grad(self.net_d, True)
        return {"loss_g": loss_g.detach(), "loss_l1": loss_l1.detach(), **losses}
