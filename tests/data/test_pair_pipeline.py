"""`tnf pair` on the real outputs of `tnf capture`, `tnf fit-scene` and `tnf touch` (tiny settings)."""

from __future__ import annotations

import numpy as np
import pytest

from tnf.data import PairDataset, open_pairs
from tnf.testing import compose


@pytest.mark.slow
def test_pair_after_real_stages(data_root):
    from tnf.stages import capture, fit_scene, pair, touch

    common = ["debug=tiny", "progress=false", "device=cpu", "object_names=[ball]"]
    capture.run(compose("capture", common))
    fit_scene.run(compose("fit-scene", common))
    touch.run(compose("touch", common))
    pair.run(compose("pair", [*common, "pair.num_novel_objects=0"]))
    a = open_pairs(data_root / "pairs" / "digit-hashgrid")
    touches = a.manifest["counts_per_object"]["ball"]
    assert len(a) == touches > 0 and a.manifest["counts"]["novel_object"] == 0
    assert a.manifest["counts"]["train"] > 0 and a.manifest["counts"]["novel_view"] > 0
    depth = a.depth.astype(np.float32)
    assert (depth[:, 63:65, 63:65].min(axis=(1, 2)) < 1).mean() > 0.5  # the centre ray mostly hits the ball
    # Depth is measured from each touch's first contact, which pair.depth_norm=contact (the default) maps to 0.5:
    # the nearest surface of a crop lies there.
    assert np.median(depth.min(axis=(1, 2))) == pytest.approx(0.5, abs=0.1)
    item = PairDataset(a.folder)[0]
    assert item["tactile"].shape == (3, 128, 128)
