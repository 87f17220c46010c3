"""The one renderer interface shared by every scene kind (fitted NeRF, hash grid, ground-truth mesh)."""

from __future__ import annotations

from typing import TypedDict

import torch


class RGBD(TypedDict):
    """What ``Scene.render_rgbd`` returns for B cameras of H x W pixels."""

    rgb: torch.Tensor  # [B, H, W, 3] float in [0, 1], composited over the scene's background colour
    depth: torch.Tensor  # [B, H, W] float, z-depth in metres along the camera's -z axis; 0 where empty
    opacity: torch.Tensor  # [B, H, W] float in [0, 1], accumulated opacity (1 = surface hit)


class Scene(torch.nn.Module):
    """A renderable object. Cameras are camera-to-world 4x4 matrices in the OpenGL convention (the camera
    looks along its -z axis, +y up), in metres, with pinhole intrinsics ``(fx, fy, cx, cy)`` in pixels."""

    def render_rgbd(
        self,
        c2w: torch.Tensor,
        intrinsics: torch.Tensor,
        width: int,
        height: int,
        chunk: int | None = None,
    ) -> RGBD:
        """Render B views. ``c2w``: [B, 4, 4]; ``intrinsics``: [B, 4] or [4]; ``chunk``: rays per batch."""
        raise NotImplementedError
