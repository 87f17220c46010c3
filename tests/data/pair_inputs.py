"""Hand-made inputs of `tnf pair` for tests: an analytic sphere scene, capture, scene and touch items."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from tnf.artifacts import ArtifactStore, write_json
from tnf.registry import SCENES, SENSORS, config_to_dict
from tnf.scenes.base import Scene

ASSETS = Path(__file__).resolve().parents[1] / "assets"


class SphereScene(Scene):
    """A sphere at the origin, ray-cast exactly in torch; colour (n + 1) / 2 of the surface normal n."""

    @dataclass
    class Config:
        radius: float = 0.04
        """Sphere radius, metres."""

    def __init__(self, cfg: Config):
        super().__init__()
        self.cfg = cfg
        self.register_buffer("radius", torch.tensor(float(cfg.radius)))

    def render_rgbd(self, c2w, intrinsics, width, height, chunk=None):
        b = c2w.shape[0]
        intr = intrinsics.expand(b, 4) if intrinsics.ndim == 1 else intrinsics
        v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
        u, v = u.float() + 0.5, v.float() + 0.5
        fx, fy, cx, cy = (intr[:, i, None, None] for i in range(4))
        d_cam = torch.stack([(u - cx) / fx, -(v - cy) / fy, -torch.ones_like(u).expand(b, -1, -1)], -1)
        d = torch.einsum("bij,bhwj->bhwi", c2w[:, :3, :3], d_cam)  # z-component of d_cam is -1: t is z-depth
        o = c2w[:, None, None, :3, 3].expand_as(d)
        a = (d * d).sum(-1)
        bb = 2 * (o * d).sum(-1)
        c = (o * o).sum(-1) - self.radius**2
        disc = bb * bb - 4 * a * c
        hit = disc >= 0
        t = (-bb - disc.clamp_min(0).sqrt()) / (2 * a)
        hit &= t > 0
        p = o + t[..., None] * d
        n = p / self.radius
        rgb = torch.where(hit[..., None], (n + 1) / 2, torch.ones_like(n))
        return {"rgb": rgb, "depth": torch.where(hit, t, torch.zeros_like(t)), "opacity": hit.float()}


# Registered so that the scene checkpoints the tests write load through tnf.scenes.load_scene.
SCENES.add("test_sphere", SphereScene, origin="tests")


def look_at(eye) -> np.ndarray:
    """Camera-to-world (OpenGL) at ``eye`` looking at the origin."""
    eye = np.asarray(eye, float)
    z = eye / np.linalg.norm(eye)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, eye
    return m


SPLIT_CYCLE = ("train", "train", "train", "val", "novel_view", "novel_view")


def touch_colour(obj_index: int, touch: int) -> tuple[int, int, int]:
    return (40 * obj_index + 20, 10 * touch, 200)


def make_inputs(
    root: Path,
    objects=("ball", "box"),
    touches: int = 6,
    distance: float = 0.1,
    radius: float = 0.04,
    scenes: bool = True,
    sensor_params: dict | None = None,
    focal: float = 60.0,
    size: int = 64,
) -> None:
    """capture/, scenes/hashgrid/ and touch/digit/ items for ``objects`` of the builtin source."""
    from tnf.scenes import save_scene

    store = ArtifactStore(root)
    from tnf.registry import split_spec
    from tnf.testing import compose

    # The sensor settings `tnf touch` would record: the configured digit (YAML defaults).
    _, params = split_spec(compose("touch", ["debug=tiny"]).sensor)
    sensor_cfg = config_to_dict(SENSORS.config("digit", {**params, **(sensor_params or {})}))
    rng = np.random.default_rng(0)
    for k, obj in enumerate(objects):
        with store.writing("capture", "builtin", obj, config={"test": 1}) as tmp:
            write_json(
                tmp / "transforms.json",
                {"fl_x": focal, "fl_y": focal, "cx": size / 2, "cy": size / 2, "w": size, "h": size, "frames": []},
            )
        if scenes:
            with store.writing("scenes", "hashgrid", "builtin", obj, config={"test": 1}) as tmp:
                save_scene(SphereScene(SphereScene.Config(radius)), tmp)
        recs = []
        with store.writing("touch", "digit", "builtin", obj, config={"test": 1}) as tmp:
            (tmp / "images").mkdir()
            Image.open(ASSETS / "bg_digit_240_320.jpg").convert("RGB").save(tmp / "background.png")
            for t in range(touches):
                direction = rng.normal(size=3)
                direction /= np.linalg.norm(direction)
                start = look_at(direction * distance)
                img = np.zeros((sensor_cfg["height"], sensor_cfg["width"], 3), np.uint8)
                img[:] = touch_colour(k, t)
                Image.fromarray(img).save(tmp / "images" / f"{t:05d}.png")
                recs.append(
                    {
                        "index": t,
                        "split": SPLIT_CYCLE[t % len(SPLIT_CYCLE)],
                        "image": f"images/{t:05d}.png",
                        "start_c2w": start.tolist(),
                        "contact_c2w": start.tolist(),
                        "contact_point": (direction * radius).tolist(),
                        "force": 5.0,
                        "penetration": 0.001,
                    }
                )
            write_json(
                tmp / "manifest.json",
                {
                    "touches": recs,
                    "sensor": {"name": "digit", "config": sensor_cfg},
                    "object": obj,
                    "source": "builtin",
                },
            )
