"""``mesh``: the ground-truth mesh as a scene, rendered by rasterisation (for the pairing ablation)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from tnf.capture.render import MeshRenderer
from tnf.registry import FROM_YAML, SCENES, yaml_defaults
from tnf.scenes.base import RGBD, Scene


class MeshScene(Scene):
    """The object's ground-truth mesh rendered with pyrender (exact RGB-D, no fitting)."""

    #: The setting that chooses it (``tnf list``): it has no ``scene=`` option, as nothing is fitted.
    chosen_by = "pair.scene_source=mesh"

    @dataclass
    @yaml_defaults("capture/default", partial=True)
    class Config:
        """Background and lights as the capture's: the defaults are those of ``conf/capture/default.yaml``."""

        background: tuple[float, float, float] = FROM_YAML
        """RGB background colour in [0, 1] where no surface is hit (match the capture's)."""
        ambient: float = FROM_YAML
        """Ambient light level in [0, 1] (match the capture's)."""
        light_intensity: float = FROM_YAML
        """Strength of the world-fixed key light (match the capture's)."""

    def __init__(self, cfg: Config, mesh: Any):
        super().__init__()
        self.cfg = cfg
        self.mesh = mesh
        self._renderers: dict[tuple[int, int], Any] = {}

    @classmethod
    def from_mesh(cls, mesh: Any, **config: Any) -> MeshScene:
        """A scene of ``mesh`` (trimesh, metres) with ``config`` overriding Config defaults."""
        return cls(SCENES.config("mesh", config), mesh)

    def render_rgbd(
        self, c2w: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int, chunk: int | None = None
    ) -> RGBD:
        """Render B views; see :meth:`Scene.render_rgbd`. ``chunk`` is ignored (whole images are rasterised)."""

        key = (int(width), int(height))
        if key not in self._renderers:
            self._renderers[key] = MeshRenderer(
                self.mesh, width, height, self.cfg.background, self.cfg.ambient, self.cfg.light_intensity
            )
        poses = c2w.detach().cpu().double().numpy()
        k = intrinsics.detach().cpu().double().numpy()
        rgb, depth = self._renderers[key].render(poses, k)
        dev = c2w.device
        depth_t = torch.from_numpy(np.ascontiguousarray(depth)).to(dev)
        return {
            "rgb": torch.from_numpy(rgb).to(dev, torch.float32) / 255.0,
            "depth": depth_t,
            "opacity": (depth_t > 0).float(),
        }
