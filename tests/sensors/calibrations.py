"""A small valid calibration for tests that need one on disk."""

import numpy as np

from tnf.sensors.calibration import Calibration


def random_calibration(seed: int = 0, width: int = 320, height: int = 240) -> Calibration:
    """A calibration of random content for a ``width`` x ``height`` sensor: a 9 x 9 shading table, a background."""
    rng = np.random.default_rng(seed)
    return Calibration(
        table=rng.normal(0, 10, (9, 9, 3)).astype(np.float32),
        max_slope=1.5,
        blur_sigma=2.0,
        noise_std=1.0,
        falloff=0.1,
        background=rng.integers(0, 256, (height, width, 3), dtype=np.uint8),
    )
