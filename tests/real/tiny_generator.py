"""A tiny generator for the tests of generated presses: ``tnf train`` with the tiny config on a small paired
dataset of the synthetic blob task (``tests.generators.synthetic``), written in the tnf.data format."""

from __future__ import annotations

from pathlib import Path

from tests.generators.test_stages import write_pairs
from tnf.testing import compose

SENSOR = ["sensor=gelsight_mini", "sensor.width=80", "sensor.height=60"]
"""The GelSight Mini at 80x60: an eighth of the taxim recording's 640x480, its pixel size matching."""
TINY = ["debug=tiny", "progress=false", "data.batch_size=4", *SENSOR]


def train_tiny_generator(root: Path) -> Path:
    """Train ``tn_cgan`` (8 filters, two short epochs) into ``root``'s store; returns its ``best.ckpt``."""
    from tnf.stages import train

    write_pairs(root / "pairs" / "synthetic", n=12)
    out = train.run(compose("train", [*TINY, f"data_root={root}", "data.datasets=[synthetic]"]))
    return Path(out["run_dir"]) / "best.ckpt"
