"""Touches at many forces: the force plan (tnf.sim.forces) and what `tnf touch` records with it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tnf.cli import main
from tnf.errors import TnfError
from tnf.registry import SENSORS
from tnf.sim.forces import BANDS, force_plan, requested_forces
from tnf.stages.touch import item_config
from tnf.testing import compose

DIGIT = SENSORS.build({"name": "digit"})


def test_defaults_come_from_the_gel_stiffness():
    p = force_plan({}, DIGIT)
    assert (p.min, p.max, p.interpolation, p.extrapolation) == (1.0, 8.0, (4.0, 5.0), (8.0, 10.0))
    # OmniTact's gel (E = 500 kPa) is 5/3 as stiff as the Digit's (300 kPa, same Poisson ratio): 5/3 the force.
    omni = force_plan({}, SENSORS.build({"name": "omnitact"}))
    assert omni.min == pytest.approx(5 / 3, abs=1e-3) and omni.max == pytest.approx(40 / 3, abs=1e-3)
    assert force_plan(None, DIGIT) is None


@pytest.mark.parametrize("dist", ["uniform", "log_uniform"])
def test_training_forces_skip_the_interpolation_band_and_test_forces_cover_every_band(dist):
    p = force_plan({"min": 1.0, "max": 8.0, "dist": dist, "interpolation": [4.0, 5.0]}, DIGIT)
    rng = np.random.default_rng(0)
    f = p.training_forces(rng, 20_000)
    assert f.min() >= 1.0 and f.max() <= 8.0
    assert not ((f > 4.0) & (f < 5.0)).any()
    assert (f < 4.0).any() and (f > 5.0).any()
    if dist == "uniform":  # the density is flat over what is left: 3 N below the band, 3 N above it
        assert abs((f < 4.0).mean() - 0.5) < 0.02
    near = p.adjacent([2.9, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5, 6.0, 6.1])
    assert near.tolist() == [False, True, True, False, False, False, True, True, False]
    t, bands = p.test_forces(rng, 300)
    assert [bands.count(b) for b in BANDS] == [100, 100, 100]
    assert p.band_of(t) == bands


@pytest.mark.parametrize(
    "spec, message",
    [
        ({"min": 8.0, "max": 1.0}, r"touch.force_range: min \(8.0 N\) must be below max \(1.0 N\)"),
        ({"min": -1.0, "max": 8.0}, r"touch.force_range.min: a force must be >= 0 N, got -1.0"),
        ({"min": float("nan"), "max": 8.0}, r"touch.force_range.min: expected a finite force, got nan"),
        ({"interpolation": [7.0, 9.0]}, r"interpolation \[7.0, 9.0\] must lie strictly inside the range"),
        ({"extrapolation": [6.0, 9.0]}, r"extrapolation \[6.0, 9.0\] must start at or above max"),
        ({"dist": "normal"}, r"touch.force_range.dist must be one of uniform, log_uniform"),
        ({"extrapolation": [8.0, 30.0]}, r"force must be in \(0.0, 20.0\] N, got 30.0"),
        ({"mx": 3}, r"unknown setting 'mx'"),
        # The default extrapolation band (max to 1.25 max) leaves the Digit's 20 N: the message names the band.
        ({"max": 19.0}, r"touch.force_range.extrapolation \[19.0, 23.75\] \(null: \[max, 1.25 max\]\): sensor 'digit'"),
    ],
)
def test_a_bad_force_range_is_one_line(spec, message):
    with pytest.raises(TnfError, match=message):
        force_plan(spec, DIGIT)


def test_the_touch_stage_refuses_a_bad_range_in_one_line(data_root, capsys):
    assert main(["touch", "debug=tiny", "progress=false", "touch.force_range={min:8.0,max:1.0}"]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: touch.force_range: min (8.0 N) must be below max (1.0 N)"
    ]


@pytest.mark.parametrize(
    "value, message",
    [
        (-1.0, "generate.touch_force: a force must be >= 0 N, got -1.0"),
        (float("nan"), "generate.touch_force: expected a finite force, got nan"),
        ("9:1:3", "needs low <= high"),
        ("heavy", "expected newtons, a list, 'low:high:count' or sim"),
        ("0:5:3", "a press needs a force > 0 N, got 0"),
        ("3.5", r"got the string '3.5'; give the force as a number, without quotes \(generate.touch_force=3.5\)"),
    ],
)
def test_a_bad_requested_force_is_one_line(value, message):
    with pytest.raises(TnfError, match=message):
        requested_forces(value, True, "m", 3.0)
    assert requested_forces("1:3:3", True, "m", 3.0) == [1.0, 2.0, 3.0]
    assert requested_forces(None, True, "m", 3.0) == [3.0] and requested_forces(None, False, "m", 3.0) is None


def test_touches_record_their_force_and_band(data_root):
    over = ["debug=tiny", "object=ball", "progress=false", "device=cpu", "touch.n_novel_view=9"]
    assert main(["touch", *over, "touch.force_range={min:1.0,max:8.0}"]) == 0
    m = json.loads((data_root / "touch" / "digit" / "builtin" / "ball" / "manifest.json").read_text())
    assert m["force_range"]["interpolation"] == [4.0, 5.0]
    touches = m["touches"]
    for t in touches:
        assert t["force"] == pytest.approx(t["force_target"], rel=0.02)  # a ball never needs the deepest press
        if t["split"] in ("train", "val"):
            assert t["force_band"] == "train" and not 4.0 < t["force_target"] < 5.0
    assert sorted(t["force_band"] for t in touches if t["split"] == "novel_view") == sorted(BANDS * 3)
    # Left at its default (null) the range is recorded as null: every touch presses with touch.force.
    cfg = compose("touch", over)
    assert item_config(cfg, DIGIT)["touch"]["force_range"] is None
    assert item_config(cfg, DIGIT)["touch"]["force"] == 3.0


def test_a_force_given_to_the_redo_switch_points_to_touch_force(data_root, capsys):
    assert main(["generate", "debug=tiny", "generate.force=3.5"]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: generate.force: expected true or false, got 3.5 (it redoes finished images; the force of a "
        "generated touch is generate.touch_force)"
    ]


@pytest.mark.parametrize(
    "stage, setting, line",
    [
        ("generate", "generate.touch_force=nan", "error: generate.touch_force: expected a finite number, got nan"),
        (
            "generate",
            "generate.touch_force=[3,nan]",
            "error: generate.touch_force[1]: expected a finite number, got nan",
        ),
        (
            "touch",
            "touch.force=25",
            "error: touch.force: sensor 'digit': force must be in (0.0, 20.0] N, got 25.0 (sensor.force_range)",
        ),
    ],
)
def test_a_bad_force_setting_names_itself_in_one_line(data_root, capsys, stage, setting, line):
    assert main([stage, "debug=tiny", "progress=false", setting]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [line]


def test_touches_that_stop_at_the_deepest_press_are_reported(data_root, capsys):
    # 19 N is inside the Digit's force range, but a box's edges and corners stop at its 3 mm max_penetration first.
    over = ["debug=tiny", "object=box", "progress=false", "device=cpu", "touch.force=19.0"]
    assert main(["touch", *over]) == 0
    out = " ".join(capsys.readouterr().out.split())
    touches = json.loads((data_root / "touch" / "digit" / "builtin" / "box" / "manifest.json").read_text())["touches"]
    short = [t for t in touches if t["force"] < 19.0 * 0.999]
    assert short and all(t["penetration"] == pytest.approx(0.003, rel=1e-4) for t in short)
    assert (
        f"warning: touch digit/builtin/box: {len(short)} of {len(touches)} touches stopped at the deepest press "
        "(sensor.max_penetration, 3 mm) short of their target force"
    ) in out
    assert "Lower touch.force or raise sensor.max_penetration" in out
