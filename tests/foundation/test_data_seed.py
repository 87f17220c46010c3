"""data_seed: the seed of the data stages, so that a sweep over seeds can train every model on one dataset."""

from __future__ import annotations

import json

from tests.reliability.helpers import QUIET, run_tnf
from tnf.testing import compose

TOUCH = [*QUIET, "object_names=[ball]"]


def touch_manifest(root) -> dict:
    return json.loads((root / "touch" / "digit" / "builtin" / "ball" / "manifest.json").read_text())


def test_a_fixed_data_seed_keeps_the_data_of_another_seed(capsys, data_root):
    assert run_tnf(capsys, "touch", *TOUCH, "seed=0")[0] == 0
    made = touch_manifest(data_root)
    # seed 1 with the data stages at seed 0: the touches of seed 0 are the ones it wants
    assert run_tnf(capsys, "touch", *TOUCH, "seed=1", "data_seed=0")[0] == 0
    assert touch_manifest(data_root) == made
    # seed 1 alone (data_seed null): its own touches, under the same item
    assert run_tnf(capsys, "touch", *TOUCH, "seed=1")[0] == 0
    remade = touch_manifest(data_root)
    assert remade["config_hash"] != made["config_hash"] and remade["config"]["seed"] == 1


def test_sim_digit_makes_its_data_once_for_every_seed():
    """The committed sim_digit runs trained seeds 0-2 on one dataset, made at seed 0."""
    for seed in (0, 1, 2):
        cfg = compose("pipeline", ["experiment=sim_digit", f"seed={seed}"])
        assert cfg.seed == seed and cfg.data_seed == 0
    assert compose("pipeline", ["seed=3"]).data_seed is None  # the quick start: each seed its own data
