"""The generator network of ``tn_cgan`` and ``lee``: one pix2pix encoder per condition, a U-Net decoder with
skip connections, an optional full-resolution head, residual output and force conditioning.

All images are [B, C, H, W] float tensors in [-1, 1].
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from tnf.errors import TnfError
from tnf.generators.nets.conditioning import CHANNELS, FORCE_MODES, ForceFiLM, coordinate_grid, force_plane
from tnf.generators.nets.gan import NoiseDropout, norm_layer


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
