"""The pipeline's estimate of the time left: expected stage times scaled by how the stages so far compared."""

import json

import pytest

from tnf.errors import TnfError
from tnf.stages.pipeline import _clock, expected_times, time_left
from tnf.testing import compose

EXPECTED = {"capture": 2.0, "fit-scene": 80.0, "touch": 2.0, "pair": 40.0, "train": 200.0}


def test_time_left_scales_the_remaining_stages_by_the_pace_so_far():
    todo = ["pair", "train"]
    assert time_left(todo, {}, EXPECTED) == pytest.approx(240.0)
    # fit-scene took twice its expected time: the rest is expected to take twice theirs too; stages of a few
    # seconds (capture, touch) are too short to set the pace
    assert time_left(todo, {"capture": 5.0, "fit-scene": 160.0, "touch": 2.0}, EXPECTED) == pytest.approx(480.0)
    assert time_left(todo, {"capture": 5.0}, EXPECTED) == pytest.approx(240.0)
    # a stage whose work the store already held (under a quarter of its time) does not set the pace
    assert time_left(todo, {"fit-scene": 0.5}, EXPECTED) == pytest.approx(240.0)
    assert time_left(["generate"], {}, EXPECTED) is None  # no expected time: no estimate


def test_expected_times_come_from_the_last_finished_run_else_the_config(tmp_path):
    cfg = compose("pipeline", ["experiment=quickstart", f"data_root={tmp_path}"])
    given = {str(k): float(v) for k, v in cfg.pipeline.expected_s.items()}
    assert "train" in given and expected_times(cfg) == given  # the experiment's own figures
    timings = tmp_path / "reports" / "quickstart" / "timings"
    timings.mkdir(parents=True)
    (timings / "unfinished.json").write_text(json.dumps({"stages": {"capture": 1.0}, "total_s": None}))
    assert expected_times(cfg) == given  # an unfinished run's times are not a whole run's
    (timings / "done.json").write_text(json.dumps({"stages": {"capture": 1.5, "train": 7.0}, "total_s": 8.5}))
    assert expected_times(cfg) == {"capture": 1.5, "train": 7.0}


def test_clock_format():
    assert _clock(5.4) == "0:05" and _clock(125) == "2:05" and _clock(3725) == "1:02:05"


@pytest.mark.parametrize("bad", ["{train: soon}", "{train: -5}", "{train: .nan}", "170"])
def test_expected_times_that_are_not_seconds_are_refused_in_one_line(tmp_path, bad):
    cfg = compose("pipeline", [f"data_root={tmp_path}", f"pipeline.expected_s={bad}"])
    with pytest.raises(TnfError, match="pipeline.expected_s"):
        expected_times(cfg)
