"""Touch-format folders made by code: tactile-like images whose content depends on the object."""

import json
from pathlib import Path

import numpy as np
from PIL import Image

from tnf.touches import TouchRecord, as_matrix


def tactile_image(label: int, rng: np.random.Generator, h: int = 240, w: int = 320) -> np.ndarray:
    """A Digit-like image: a bluish background with an indentation blob whose shape depends on ``label``
    (0: round, 1: a horizontal bar, 2: a vertical bar), at a random position, plus pixel noise."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([60 + 0.1 * xx, 90 + 0.05 * yy, np.full((h, w), 150.0)], -1)
    cy, cx = rng.uniform(0.3, 0.7) * h, rng.uniform(0.3, 0.7) * w
    sy, sx = [(30, 30), (12, 70), (70, 12)][label % 3]
    blob = np.exp(-(((yy - cy) / sy) ** 2 + ((xx - cx) / sx) ** 2))
    img += blob[..., None] * np.array([80.0, 60.0, -40.0])
    img += rng.normal(0, 4, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def write_touch_folder(folder: Path, obj: str, label: int, splits: dict[str, int], seed: int = 0) -> Path:
    """A touch-format folder (images/*.png + manifest.json with a 'touches' list) for object ``obj``."""
    rng = np.random.default_rng(seed * 100 + label)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    touches = []
    for split, n in splits.items():
        for _ in range(n):
            i = len(touches)
            Image.fromarray(tactile_image(label, rng)).save(folder / "images" / f"{i:05d}.png")
            touches.append(
                TouchRecord(index=i, split=split, image=f"images/{i:05d}.png", start_c2w=as_matrix(np.eye(4))).to_json()
            )
    (folder / "manifest.json").write_text(json.dumps({"object": obj, "touches": touches}))
    return folder
