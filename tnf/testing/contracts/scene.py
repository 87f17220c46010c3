"""The scene contract suite."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest

from tnf.cameras import look_at
from tnf.registry import (
    SCENES,
)
from tnf.scenes import load_scene, save_scene
from tnf.testing.contracts.base import _ComponentContract


# -- scenes -----------------------------------------------------------------------------------------
class SceneContract(_ComponentContract):
    """A scene (``tnf.scenes.base.Scene``) renders RGB-D with the documented shapes and ranges.

    Checks: registration and documented Config; config round trip; ``render_rgbd`` for B cameras looking at
    the origin gives rgb ``[B, H, W, 3]`` in [0, 1], depth ``[B, H, W]`` >= 0 and opacity ``[B, H, W]`` in
    [0, 1], all finite float32; ``intrinsics`` may be ``[4]`` or ``[B, 4]``; a registered scene saves and
    loads back by name (``save_scene`` / ``load_scene``) and renders the same. Override the ``scene`` fixture
    for a scene that needs more than its config (e.g. a mesh); set ``params`` to make it tiny.
    """

    registry = SCENES
    width: ClassVar[int] = 16
    height: ClassVar[int] = 12
    distance: ClassVar[float] = 0.3
    """Camera distance from the origin, metres (scenes are objects of a few centimetres at the origin)."""
    saveable: ClassVar[bool] = True
    """Whether ``save_scene`` / ``load_scene`` apply (false for scenes built from data they do not store)."""

    @pytest.fixture
    def scene(self) -> Any:
        import torch

        torch.manual_seed(0)
        return SCENES.build(self.spec()).eval()

    def cameras(self, batch: int = 2) -> tuple[Any, Any]:
        """``c2w [B, 4, 4]`` looking at the origin from around it, and intrinsics ``[4]`` (45 degree vertical fov)."""
        import torch

        eyes = [(self.distance, 0.0, 0.05), (0.0, -self.distance, 0.1), (0.0, 0.0, self.distance)][:batch]
        c2w = torch.tensor(
            np.stack([look_at(np.array(e), np.zeros(3), fallback="parallel") for e in eyes]), dtype=torch.float32
        )
        f = 0.5 * self.height / np.tan(np.radians(22.5))
        return c2w, torch.tensor([f, f, self.width / 2, self.height / 2], dtype=torch.float32)

    def _check(self, out: Any, batch: int) -> None:
        import torch

        h, w = self.height, self.width
        assert set(out) >= {"rgb", "depth", "opacity"}
        assert out["rgb"].shape == (batch, h, w, 3)
        assert out["depth"].shape == out["opacity"].shape == (batch, h, w)
        for k in ("rgb", "depth", "opacity"):
            assert out[k].dtype == torch.float32 and torch.isfinite(out[k]).all(), k
        assert out["rgb"].min() >= 0 and out["rgb"].max() <= 1
        assert out["opacity"].min() >= 0 and out["opacity"].max() <= 1 + 1e-5
        assert out["depth"].min() >= 0

    def test_render_rgbd_shapes_and_ranges(self, scene):
        import torch

        c2w, k = self.cameras(2)
        with torch.no_grad():
            self._check(scene.render_rgbd(c2w, k, self.width, self.height), 2)
            self._check(scene.render_rgbd(c2w[:1], k[None], self.width, self.height, chunk=37), 1)

    def test_save_and_load_by_name(self, scene, tmp_path):
        import torch

        if not self.saveable:
            pytest.skip(f"{self.name} scenes are not saved as checkpoints")

        path = save_scene(scene, tmp_path)
        blob = torch.load(path, map_location="cpu", weights_only=True)
        assert blob["name"] == self.name
        loaded = load_scene(tmp_path)
        c2w, k = self.cameras(1)
        with torch.no_grad():
            a = scene.render_rgbd(c2w, k, self.width, self.height)
            b = loaded.render_rgbd(c2w, k, self.width, self.height)
        for key in ("rgb", "depth", "opacity"):
            assert torch.allclose(a[key], b[key], atol=1e-5), key
