"""``tn_cgan``: the Touch-NeRF conditional GAN (the paper's Fig. 2).

The RGB image, the depth image (by default with its slopes) and the sensor's background image go through
separate convolutional encoders; their innermost features are concatenated and decoded by a U-Net decoder into
the tactile image, with skip connections from the background and depth encoders (configurable) at every
scale. A PatchGAN discriminator judges (condition, tactile) pairs; the generator minimises the cGAN loss plus
lambda_L1 times the L1 distance to the real image, plus lambda_SSIM times (1 - SSIM).

Seven defaults depart from the paper's figure, chosen on the validation split of ``sim_digit`` (seed 0, 30
epochs, results/generators/tn_cgan_variants.md): the paper's layout (skips from the background encoder only,
dropout 0.5 as the noise z, kept on when generating) scored SSIM 0.920 / MSE 195; depth skips 0.926 / 168;
depth skips without dropout 0.942 / 125. With contact-framed inputs that last layout scored 0.946 / 110, a
full-resolution head 0.952 / 97, both with an SSIM loss term of weight 60 0.959 / 94. A residual output (the
network draws the change to the background image) then scored 0.962 / 90 against 0.956 / 102 on one machine's
data; three more seeds on another machine scored 0.954-0.962. Without the adversarial term
(``lambda_gan=0``, the default: the discriminator is built but neither run nor trained) one seed scored
0.970 / 64 against 0.961 / 90 with it, and two more seeds led every run with it at matched epochs. The term
does carry object-specific detail: a classifier trained on the generated images alone scored 41 % on
validation touches without it, 55 % with it and 50 % at ``lambda_gan=0.1`` (SSIM 0.968; one seed each), so
generated data meant to train a model is better made with the term. Last, the depth encoder sees the depth
image with its slopes (``depth_and_slope``): at sim_digit's full schedule (45 epochs, three seeds) validation
MSE fell from 56.9 to 53.1 and the generated images alone trained a classifier to 48.5 % instead of 45.3 %.
The paper's layout is ``inputs=[rgb,depth,background] skips=[background] dropout=0.5 lambda_ssim=0
full_res_head=false residual=false lambda_gan=1``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from torch import nn

from tnf.errors import TnfError
from tnf.eval import metrics
from tnf.generators.base import Generator, Optimisation
from tnf.generators.field import SurfaceField
from tnf.generators.nets import NoiseDropout, PatchDiscriminator, init_weights, norm_layer

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


def level_channels(ngf: int, level: int) -> int:
    """Feature channels at encoder level ``level`` (0 = first, half resolution): ngf, 2ngf, 4ngf, 8ngf, 8ngf..."""
    return ngf * min(2**level, 8)


class Encoder(nn.Module):
    """pix2pix encoder: ``num_downs`` 4x4 stride-2 convolutions, [B, C, H, W] -> features per level.

    Level i has ``level_channels(ngf, i)`` channels at H / 2**(i+1); the last is the 1 x 1 bottleneck for
    H = 2**num_downs. The first and the innermost convolutions have no normalisation (as pix2pix).
    """

    def __init__(self, in_ch: int, ngf: int, num_downs: int, norm: str, kernel: int = 4):
        super().__init__()
        nl = norm_layer(norm)
        use_bias = norm != "batch"
        pad = (kernel - 1) // 2
        blocks: list[nn.Module] = [nn.Conv2d(in_ch, ngf, kernel, 2, pad, bias=use_bias)]
        for i in range(1, num_downs):
            cin, cout = level_channels(ngf, i - 1), level_channels(ngf, i)
            innermost = i == num_downs - 1
            # Not in-place: the block's input is also a skip feature.
            layers: list[nn.Module] = [nn.LeakyReLU(0.2), nn.Conv2d(cin, cout, kernel, 2, pad, bias=use_bias)]
            if not innermost:
                layers.append(nl(cout))
            blocks.append(nn.Sequential(*layers))
        self.blocks = nn.ModuleList(blocks)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        feats = []
        for b in self.blocks:
            x = b(x)
            feats.append(x)
        return feats


def _out_channels(conv: nn.Module) -> int:
    assert isinstance(conv, (nn.Conv2d, nn.ConvTranspose2d))
    return int(conv.out_channels)


class UNetDecoder(nn.Module):
    """U-Net decoder from a concatenated bottleneck, with skip features concatenated at every level.

    Args:
        bottleneck_ch: channels of the 1 x 1 (or 2**-num_downs) bottleneck.
        skip_ch: channels concatenated at each level 0..num_downs-2 (0 for no skip).
        dropout_blocks: how many of the innermost up-blocks apply ``NoiseDropout(dropout)``.
        image_out: the last block makes an image with ``out_ch`` channels; false ends it in a norm layer
            (features for a further head).
        tanh: the image ends in tanh (in [-1, 1]); false leaves it linear (a residual added to another image).
    """

    def __init__(
        self,
        bottleneck_ch: int,
        skip_ch: list[int],
        ngf: int,
        num_downs: int,
        out_ch: int,
        norm: str,
        dropout: float,
        dropout_blocks: int,
        kernel: int = 4,
        image_out: bool = True,
        tanh: bool = True,
    ):
        super().__init__()
        nl = norm_layer(norm)
        use_bias = norm != "batch"
        pad, out_pad = (kernel - 1) // 2, kernel % 2  # exact 2x upsampling for 4x4 and 5x5 kernels
        blocks = []
        cin = bottleneck_ch
        for k, level in enumerate(reversed(range(num_downs))):  # level of the input's resolution
            last = level == 0
            to_image = last and image_out
            cout = out_ch if last else level_channels(ngf, level - 1)
            layers: list[nn.Module] = [
                nn.ReLU(True),
                nn.ConvTranspose2d(cin, cout, kernel, 2, pad, output_padding=out_pad, bias=use_bias or last),
            ]
            if to_image:
                if tanh:
                    layers.append(nn.Tanh())
            else:
                layers.append(nl(cout))
                if not last and k < dropout_blocks and dropout > 0:
                    layers.append(NoiseDropout(dropout))
            blocks.append(nn.Sequential(*layers))
            if not last:
                cin = cout + skip_ch[level - 1]
        self.blocks = nn.ModuleList(blocks)
        # Each block's output channels (its transposed convolution's).
        self.out_channels = [_out_channels(b[1]) for b in blocks]

    def forward(
        self,
        bottleneck: torch.Tensor,
        skips: list[list[torch.Tensor]],
        modulate: Callable[[int, torch.Tensor], torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """``skips[level]``: tensors to concatenate after upsampling to ``level``'s resolution. ``modulate(k, x)``
        (FiLM, ``ForceFiLM``) rewrites block ``k``'s output before its skips join it."""
        x = bottleneck
        n = len(self.blocks)
        for k, block in enumerate(self.blocks):
            x = block(x)
            if modulate is not None:
                x = modulate(k, x)
            level = n - 2 - k
            if level >= 0 and skips[level]:
                x = torch.cat([x, *skips[level]], 1)
        return x


class MultiEncoderUNet(nn.Module):
    """The generator network: one encoder per input, concatenated bottleneck, U-Net decoder with skip
    connections from the encoders named in ``skips``.

    ``forward(inputs)`` takes a dict with the input keys ([B, C_k, H, W] each) and returns [B, 3, H, W] in
    [-1, 1]; H = W = 2**num_downs.

    With ``full_res_head`` the decoder ends in ``ngf`` feature channels at full resolution; the skip inputs'
    images themselves (the full-resolution depth, say) are concatenated to them, and two 3 x 3 convolutions
    make the image. Without it the decoder's last transposed convolution makes the image, and the inputs'
    full-resolution pixels reach it only through the encoders' first stride-2 convolutions.

    With ``residual`` the network's last layer has no tanh and its output is added to the background image (the
    simulator's own image formation: the background plus a change where the gel is pressed), so where nothing
    touches the gel the output is the background from the start; in eval mode the sum is clipped to [-1, 1].

    The inputs named in ``coords`` get two more channels, the pixel's position (``coordinate_grid``), before
    their encoder and, for skip inputs, in the head. ``channels`` gives the channels of inputs whose count is
    not fixed (``surface``).
    """

    def __init__(
        self,
        inputs: list[str],
        skips: list[str],
        ngf: int,
        num_downs: int,
        norm: str,
        dropout: float,
        dropout_blocks: int,
        kernel: int = 4,
        full_res_head: bool = False,
        residual: bool = False,
        coords: tuple[str, ...] | list[str] = (),
        residual_on: str = "background",
        channels: dict[str, int] | None = None,
        force: str = "none",
    ):
        super().__init__()
        if force not in FORCE_MODES:
            raise ValueError(f"force must be one of {', '.join(FORCE_MODES)}, got {force!r}")
        self.force = force
        if residual and residual_on not in inputs:
            raise ValueError(f"residual output adds to the {residual_on} image: inputs {inputs} must include it")
        self.residual = residual
        self.residual_on = residual_on
        self.inputs = tuple(inputs)
        self.skips = tuple(skips)
        self.coords = tuple(coords)
        n = num_downs
        # Not saved in checkpoints: made again from the image size.
        self.position_grid: torch.Tensor
        self.register_buffer("position_grid", coordinate_grid(2**n), persistent=False)
        channels = {**CHANNELS, **(channels or {})}
        ch = {k: channels[k] + 2 * (k in self.coords) + (force == "plane") for k in self.inputs}
        self.encoders = nn.ModuleDict({k: Encoder(ch[k], ngf, n, norm, kernel) for k in self.inputs})
        bottleneck = len(self.inputs) * level_channels(ngf, n - 1)
        skip_ch = [len(self.skips) * level_channels(ngf, lv) for lv in range(n - 1)]
        dec_out = ngf if full_res_head else 3
        self.decoder = UNetDecoder(
            bottleneck,
            skip_ch,
            ngf,
            n,
            dec_out,
            norm,
            dropout,
            dropout_blocks,
            kernel,
            image_out=not full_res_head,
            tanh=not residual,
        )
        self.film: ForceFiLM | None = None
        if force == "film":  # the bottleneck and every decoder block's output
            self.film = ForceFiLM([bottleneck, *self.decoder.out_channels[: n - (not full_res_head)]])
        self.head: nn.Module | None = None
        if full_res_head:
            cin = ngf + sum(ch[k] for k in self.skips)
            self.head = nn.Sequential(
                nn.ReLU(True),
                nn.Conv2d(cin, ngf, 3, 1, 1, bias=norm != "batch"),
                norm_layer(norm)(ngf),
                nn.ReLU(True),
                nn.Conv2d(ngf, 3, 3, 1, 1),
                nn.Identity() if residual else nn.Tanh(),
            )

    def _head(self, features: torch.Tensor, images: list[torch.Tensor]) -> torch.Tensor:
        """``head(cat([features, *images]))``, with the first convolution split by input channels (a convolution is
        a sum over them): on an H100 the 128 px, ngf + 4 channel concatenation in channels-last memory took about
        a fifth of a generation pass's GPU time."""
        assert isinstance(self.head, nn.Sequential)
        relu, conv = self.head[0], self.head[1]
        assert isinstance(conv, nn.Conv2d)
        c = features.shape[1]
        y = F.conv2d(relu(features), conv.weight[:, :c], conv.bias, conv.stride, conv.padding)
        if images:  # skips=[]: the head sees the decoder's features only
            small = torch.cat(images, 1).to(features.dtype)  # autocast: bf16 features, float32 images
            y = y + F.conv2d(relu(small), conv.weight[:, c:], None, conv.stride, conv.padding)
        return self.head[2:](y)

    def forward(self, inputs: dict[str, torch.Tensor], force: torch.Tensor | None = None) -> torch.Tensor:
        """``force``: [B] the normalised force (``force_input``), needed when the network was built with one."""
        base = inputs.get(self.residual_on)
        if self.force != "none" and force is None:
            raise TnfError("this generator is conditioned on the force: its batches need the force (batch key force)")
        if self.force == "plane":
            assert force is not None
            inputs = {k: torch.cat([v, force_plane(force, v)], 1) for k, v in inputs.items()}
        if self.coords:
            grid = self.position_grid
            inputs = {
                k: torch.cat([v, grid.to(v.dtype).expand(len(v), -1, -1, -1)], 1) if k in self.coords else v
                for k, v in inputs.items()
            }
        feats = {k: self.encoders[k](inputs[k]) for k in self.inputs}
        bottleneck = torch.cat([feats[k][-1] for k in self.inputs], 1)
        n = len(next(iter(feats.values())))
        skips = [[feats[k][lv] for k in self.skips] for lv in range(n - 1)]
        modulate = None
        if self.film is not None:
            assert force is not None
            film = self.film(force)
            bottleneck = film(0, bottleneck)
            last = len(film.params) - 1

            def modulate(k: int, x: torch.Tensor) -> torch.Tensor:
                return film(k + 1, x) if k < last else x

        out = self.decoder(bottleneck, skips, modulate)
        if self.head is not None:
            out = self._head(out, [inputs[k] for k in self.skips])
        if not self.residual:
            return out
        assert base is not None  # checked in __init__
        out = base + out
        # Training sees the unclipped sum, so that the L1 and SSIM terms still pull back a pixel that overshoots.
        return out if self.training else out.clamp(-1, 1)


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


class TNcGAN(Generator):
    """Touch-NeRF cGAN: separate RGB / depth / background encoders, U-Net decoder, PatchGAN, cGAN + L1 + SSIM loss."""

    # Checkpoints written before these options existed hold the network without the head, trained without SSIM.
    added_fields: ClassVar[dict[str, Any]] = {
        "full_res_head": False,
        "lambda_ssim": 0.0,
        "residual": False,
        "lambda_gan": 1.0,
    }

    @dataclass
    class Config:
        inputs: list[str] = field(default_factory=lambda: ["rgb", "depth_and_slope", "background"])
        """Conditions, each with its own encoder: any of rgb, depth, background (drop some for ablations),
        depth_slope, the depth image's x and y slopes (``depth_slope``), which a lit gel's image follows, and
        depth_and_slope, the two together for one encoder (the default, in place of the paper's depth); prior,
        the simulator's image of the depth crop (datasets made with ``pair.prior=true``), and surface, the
        features of a surface field learned with the generator (datasets made with ``pair.points=true``)."""
        skips: list[str] = field(default_factory=lambda: ["background", "depth_and_slope"])
        """Inputs whose encoder features are skip-connected to the decoder (the paper: background only). Depth
        skips place the imprint's edges from the depth image at every scale, not from the 1 x 1 bottleneck."""
        image_size: int = 128
        """Input and output image size in pixels (square, a power of two)."""
        ngf: int = 64
        """Channels of the first encoder/last decoder layer (doubling per level up to 8 x ngf)."""
        ndf: int = 64
        """Channels of the discriminator's first layer."""
        d_layers: int = 3
        """PatchGAN depth: 3 gives 70 x 70 pixel patches."""
        norm: str = "batch"
        """Normalisation in generator and discriminator: batch, instance or none."""
        dropout: float = 0.0
        """Dropout probability in the innermost decoder blocks (the noise z; pix2pix and the paper: 0.5)."""
        dropout_blocks: int = 3
        """How many innermost decoder blocks have dropout (pix2pix: 3)."""
        dropout_at_generation: bool = True
        """Keep dropout on when generating (the noise z), as pix2pix; false for deterministic outputs."""
        gan_mode: str = "vanilla"
        """Adversarial loss: vanilla (sigmoid cross-entropy, the paper's Eq. 3) or lsgan."""
        lambda_gan: float = 0.0
        """Weight of the adversarial term in the generator's loss (the paper: 1). 0, the default, trains the
        generator as a plain regression on the L1 and SSIM terms: the discriminator then has no optimiser and is
        never run."""
        lambda_l1: float = 100.0
        """Weight lambda of the L1 loss (Eq. 2)."""
        lambda_ssim: float = 60.0
        """Weight of an SSIM loss, 1 - SSIM (the evaluation's window and constants), added to the generator's
        loss (0: the paper's cGAN + L1 loss only)."""
        full_res_head: bool = True
        """End the decoder in two 3 x 3 convolutions at full resolution that also see the skip inputs' own
        images (the 128 px depth, say); false: the decoder's last transposed convolution makes the image."""
        residual: bool = True
        """Add the network's output to an input image (``residual_on``) instead of making the image outright:
        only the change that the press makes (or what the prior gets wrong) is learned."""
        residual_on: str = "background"
        """The input image the residual output adds to: background, or prior (the simulator's image of the depth
        crop, ``pair.prior=true``). It must be in inputs."""
        coords: list[str] = field(default_factory=list)
        """Inputs that also get each pixel's x and y position as two channels (``coordinate_grid``), for their
        encoder and, if skipped, the head: where on the gel a pixel lies changes how a press there looks (the
        gel's sag, the lights' directions). Empty: the network sees positions only through its borders."""
        force: str = "none"
        """How the generator sees each touch's force (datasets made with ``pair.force=true``; docs/force.md):
        none, film (FiLM on the bottleneck and the decoder's features) or plane (a constant input plane)."""
        force_center: float = 4.5
        """With a force: the force (newtons) that maps to 0; the training range's middle."""
        force_scale: float = 3.5
        """With a force: the force span (newtons) that maps to 1; the training range's half width."""
        surface_levels: int = 5
        """With ``surface`` in inputs: the surface field's grid levels (``tnf.generators.field``)."""
        surface_features: int = 2
        """With ``surface``: features per grid vertex and level (the input has levels x features channels)."""
        surface_coarsest: float = 0.008
        """With ``surface``: the coarsest grid cell, metres."""
        surface_finest: float = 0.0005
        """With ``surface``: the finest grid cell, metres."""
        surface_log2_table: int = 20
        """With ``surface``: hash table entries per level, as a power of two."""
        surface_dropout: float = 0.25
        """With ``surface``: the share of training pairs whose field features are zeroed, so that the generator
        also works for objects the field never saw."""
        surface_lr: float = 0.005
        """With ``surface``: Adam learning rate of the field's table (hash grids learn at far larger rates than
        convolutions)."""
        lr: float = 2e-4
        """Adam learning rate of generator and discriminator."""
        beta1: float = 0.5
        """Adam beta1."""
        beta2: float = 0.999
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
            loss_g_gan = gan_loss(self.net_d(torch.cat([cond, fake], 1)), True, self.cfg.gan_mode)
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
