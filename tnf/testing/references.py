"""Plain reference forms of optimised library code, for the tests that check an optimisation changes nothing and
the benchmarks that time it."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from tnf.data.preprocess import SIZE, resize_uint8
from tnf.eval.classify import subset
from tnf.touches import read_touch_records


def load_touch_images_one_by_one(
    folder: Path, size: int, splits: Sequence[str] | None = None, limit: int | None = None, seed: int = 0
) -> torch.Tensor:
    """``tnf.eval.classify.load_touch_images`` as one loop: every image decoded and resized alone, to ``SIZE``
    and then to ``size``. Returns ``[N, 3, size, size]`` uint8."""
    recs = [t for t in read_touch_records(folder) if splits is None or t.split in splits]
    recs = [recs[i] for i in subset(len(recs), limit, seed)]
    out = np.zeros((len(recs), size, size, 3), np.uint8)
    for i, t in enumerate(recs):
        with Image.open(Path(folder) / t.image) as im:
            img = resize_uint8(np.array(im.convert("RGB")), SIZE)
        out[i] = img if size == SIZE else resize_uint8(img, size)
    return torch.from_numpy(out).permute(0, 3, 1, 2).contiguous()
