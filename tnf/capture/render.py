"""Rasterise a mesh into RGB-D with pyrender offscreen (EGL: Mesa on a CPU, the driver on a GPU).

One ``MeshRenderer`` keeps one OpenGL context and scene for many views, which is what makes capture fast.
Lights are fixed in the world (not to the camera), so an object's shading is the same in every view, as a
scene representation fitted to the images expects.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from tnf.env import headless_rendering

# Directions the world-fixed directional lights shine along (key, fill, rim), and their relative strengths.
_LIGHTS = (((-0.4, -0.5, -1.0), 1.0), ((0.8, 0.3, -0.2), 0.5), ((0.0, 0.9, 0.6), 0.35))


def _look_along(direction: Sequence[float]) -> np.ndarray:
    """A 4x4 pose whose -z axis points along ``direction`` (pyrender lights shine along their -z)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, -d)
    x /= np.linalg.norm(x)
    y = np.cross(-d, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, y, -d
    return pose


class MeshRenderer:
    """Render a ``trimesh.Trimesh`` from many cameras at ``width`` x ``height`` pixels.

    Args:
        mesh: the object, metres, with vertex colours or a texture.
        width, height: image size in pixels.
        background: RGB in [0, 1] where no surface is hit.
        ambient: ambient light level in [0, 1].
        light_intensity: strength of the key directional light (W/m^2 in pyrender's units).
    """

    def __init__(
        self,
        mesh: Any,
        width: int,
        height: int,
        background: Sequence[float] = (1.0, 1.0, 1.0),
        ambient: float = 0.35,
        light_intensity: float = 3.0,
    ):
        headless_rendering()
        import pyrender

        self.width, self.height = int(width), int(height)
        self.background = np.asarray(background, dtype=float)
        self._scene = pyrender.Scene(bg_color=[*self.background, 0.0], ambient_light=[ambient] * 3)
        self._scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False))
        for direction, strength in _LIGHTS:
            light = pyrender.DirectionalLight(color=np.ones(3), intensity=light_intensity * strength)
            self._scene.add(light, pose=_look_along(direction))
        # Near/far planes from the mesh size: tight planes keep depth precise.
        self._radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
        self._camera = pyrender.IntrinsicsCamera(1.0, 1.0, 0.5, 0.5, znear=0.01, zfar=100.0)
        self._cam_node = self._scene.add(self._camera, pose=np.eye(4))
        self._renderer = pyrender.OffscreenRenderer(self.width, self.height)

    def render(self, c2w: Any, intrinsics: Any) -> tuple[np.ndarray, np.ndarray]:
        """Render B views.

        Args:
            c2w: [B, 4, 4] or [4, 4] camera-to-world, OpenGL convention (camera looks along -z, +y up), metres.
            intrinsics: [4] or [B, 4] pinhole ``(fx, fy, cx, cy)`` in pixels, row 0 at the top of the image.

        Returns:
            rgb: [B, H, W, 3] uint8, the background colour where empty.
            depth: [B, H, W] float32 z-depth in metres along the camera's -z axis, 0 where empty.
        """
        c2w = np.asarray(c2w, dtype=float)
        if c2w.ndim == 2:
            c2w = c2w[None]
        k = np.broadcast_to(np.asarray(intrinsics, dtype=float), (len(c2w), 4))
        rgbs = np.empty((len(c2w), self.height, self.width, 3), np.uint8)
        depths = np.empty((len(c2w), self.height, self.width), np.float32)
        for i, (pose, (fx, fy, cx, cy)) in enumerate(zip(c2w, k)):
            dist = float(np.linalg.norm(pose[:3, 3]))
            self._camera.fx, self._camera.fy, self._camera.cx, self._camera.cy = fx, fy, cx, cy
            self._camera.znear = max(1e-3, 0.5 * (dist - self._radius))
            self._camera.zfar = dist + 2 * self._radius + 1e-2
            self._scene.set_pose(self._cam_node, pose)
            colour, depth = self._renderer.render(self._scene)
            rgbs[i] = colour[..., :3]
            depths[i] = depth
        return rgbs, depths

    def close(self) -> None:
        """Free the OpenGL context (also done when the renderer is garbage-collected)."""
        r = getattr(self, "_renderer", None)
        if r is not None:
            r.delete()
            self._renderer = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: the GL library may already be gone
            pass
