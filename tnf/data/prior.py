"""The simulator's own image of a rendered depth crop: a physics prior for the generator (``pair.prior``).

A pair's depth crop (``crop_extent=sensor``, ``depth_norm=contact``) shows exactly the gel patch of the tactile
image, pixel for pixel, with depth measured from the first contact. Resampled onto the sensor's pixel grid and
offset by the gel's own bulge (``Sensor.gel_surface``), it is the height field that the tactile simulator's ray
cast would give for the scene's surface; pressing the gel onto it (``WarpGel.press_heights``) with the touch's
force gives the image the sensor would show if the fitted scene's depth were the object. The generator then
learns what that image gets wrong (the scene's depth errors, the camera's perspective, what the crop misses)
rather than the gel's mechanics and lighting.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from tnf.data.preprocess import SIZE, resize_uint8
from tnf.errors import TnfError
from tnf.registry import SIMULATORS


class DepthPrior:
    """Tactile images ``[B, 128, 128, 3]`` uint8 of depth crops ``[B, 128, 128]`` in [0, 1] (1 = no surface).

    Args:
        sensor: the tactile sensor (``tnf.sensors``) the crops were framed for.
        simulator: its simulator config node (``{"name": "warp_gel", ...}``; ``cfg.simulator``).
        framing: the crops' ``tnf.data.render.Framing``: it must be ``crop_extent=sensor`` with
            ``depth_norm=contact`` (the crop is the tactile image's patch and its depth is metric).
        device: warp device of the simulator (``cpu``, ``cuda:0``).
        batch: crops pressed per simulator call (bounds memory).
    """

    def __init__(self, sensor: Any, simulator: Any, framing: Any, device: str = "cpu", batch: int = 256):
        if framing.crop_extent != "sensor" or framing.depth_norm != "contact":
            raise TnfError(
                "pair.prior needs crops pixel-aligned with the tactile image and metric depth: set "
                f"pair.crop_extent=sensor and pair.depth_norm=contact (got {framing.crop_extent}, {framing.depth_norm})"
            )
        # The prior is the mean image: without the sensor's pixel noise.
        noiseless = type(sensor)(replace(sensor.cfg, noise_std=0.0)) if sensor.cfg.noise_std else sensor
        self.sim = SIMULATORS.build(simulator, sensor=noiseless, device=device)
        if not callable(getattr(self.sim, "press_heights", None)):
            raise TnfError(
                f"pair.prior presses the gel onto height fields (press_heights), which simulator "
                f"{type(self.sim).__name__} does not offer; warp_gel does"
            )
        self.sensor = noiseless
        self.window = float(framing.depth_window)
        self.batch = int(batch)
        # How far each pixel's gel point bulges toward the object: it meets the surface that much sooner.
        self._bulge = torch.from_numpy(noiseless.gel_surface().astype(np.float32))

    def __call__(self, depth: np.ndarray | torch.Tensor, force: float | np.ndarray) -> np.ndarray:
        """The images of ``depth`` crops [B, 128, 128] in [0, 1], pressed with ``force`` newtons (scalar or [B])."""
        d = torch.as_tensor(depth).detach().float().cpu()
        if d.ndim != 3 or d.shape[1:] != (SIZE, SIZE):
            raise TnfError(f"depth crops must be [B, {SIZE}, {SIZE}], got {list(d.shape)}")
        f = np.broadcast_to(np.asarray(force, dtype=np.float32), (len(d),))
        out = np.empty((len(d), SIZE, SIZE, 3), np.uint8)
        for s in range(0, len(d), self.batch):
            e = s + self.batch
            out[s:e] = resize_uint8(self.sim.press_heights(self.gaps(d[s:e]), f[s:e]).images, SIZE)
        return out

    def gaps(self, depth: torch.Tensor) -> np.ndarray:
        """``[B, H, W]`` metres from each gel pixel to the surface (inf where none), the sensor's pixel grid."""
        s = self.sensor
        size = (s.height, s.width)
        hit = F.interpolate((depth < 1).float()[:, None], size=size, mode="bilinear", align_corners=False)[:, 0]
        rel = F.interpolate(depth[:, None], size=size, mode="bilinear", align_corners=False)[:, 0]
        g = (rel - 0.5) * self.window - self._bulge
        # A pixel next to an empty one mixes in the empty depth: only pixels with all neighbours on a surface.
        return torch.where(hit > 0.999, g, torch.full_like(g, float("inf"))).numpy()
