"""Network parts shared by the generators: norms, noise dropout, PatchGAN, ResNet blocks, image pool, the
conditions a generator sees (``conditions``), the multi-encoder U-Net, force FiLM and the GAN losses.

All images are [B, C, H, W] float tensors in [-1, 1].
"""

from __future__ import annotations

import functools
import random
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from tnf.errors import TnfError
from tnf.generators.field import SurfaceField


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
