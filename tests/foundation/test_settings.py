"""The stage sections and run-wide settings are checked by their settings classes before any stage works
(tnf.stages.settings)."""

from pathlib import Path

import pytest

from tnf.cli import main
from tnf.errors import TnfError
from tnf.registry import defaults_source
from tnf.stages.settings import TYPED, check_settings, settings_class
from tnf.testing import compose

EXPERIMENTS = sorted(p.stem for p in (Path(__file__).resolve().parents[2] / "conf" / "experiment").glob("*.yaml"))


@pytest.mark.parametrize(
    "override, message",
    [
        ("train.epochs=abc", "train.epochs: expected a whole number, got 'abc'"),
        ("touch.n_touches=-5", "touch.n_touches: must be >= 0, got -5"),
        ("evaluate.classify.sim_per_object=0", "evaluate.classify.sim_per_object: must be >= 1, got 0"),
        ("touch.n_touches=1.5", "touch.n_touches: expected a whole number, got 1.5"),
        ("touch.force=nan", "touch.force: expected a finite number, got nan"),
        ("touch.random_roll=maybe", "touch.random_roll: expected true or false, got 'maybe'"),
        ("data.augment=mirror", "data.augment: expected a list, got 'mirror'"),
        ("progress=2", "progress: expected true or false, got 2"),
        ("seed=-1", "seed: must be >= 0, got -1"),
        ("fit.steps=1.5", "fit.steps: expected a whole number, got 1.5"),
        ("capture.fov_deg=abc", "capture.fov_deg: expected a number, got 'abc'"),
        (
            "pipeline.stages=[touch,frobnicate]",
            "pipeline.stages: unknown stage 'frobnicate'; stages: calibrate, capture, fit-scene, touch, pair, train, "
            "finetune, generate, evaluate",
        ),
        ("pipeline.expected_s={train: soon}", "pipeline.expected_s.train: expected a number, got 'soon'"),
        (
            "train.compile=fast",
            "train.compile: expected true, false or one of default, reduce-overhead, max-autotune, "
            "max-autotune-no-cudagraphs, got 'fast'",
        ),
    ],
)
def test_a_bad_setting_is_one_line_before_any_work(override, message, capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    assert main(["touch", "debug=tiny", override]) == 1
    assert capsys.readouterr().err.strip().splitlines() == [f"error: {message}"]
    assert list(tmp_path.iterdir()) == []  # not even Hydra's log folder


@pytest.mark.parametrize("experiment", [None, *EXPERIMENTS])
def test_every_shipped_config_passes(experiment):
    overrides = [f"experiment={experiment}"] if experiment else []
    if experiment == "real_capture":
        overrides.append("objects.root=/data")
    for debug in ([], ["debug=tiny"]):
        check_settings(compose("pipeline", overrides + debug))


def test_every_stage_section_is_typed():
    """Every section with a ``conf/<section>/default.yaml`` but the callbacks group is a stage's, validated into
    the settings class that takes its defaults from that file."""
    conf = Path(__file__).resolve().parents[2] / "conf"
    sections = sorted(p.parent.name for p in conf.glob("*/default.yaml") if p.parent.name != "callbacks")
    assert sections == sorted(TYPED)
    for section in sections:
        cls = settings_class(section)
        assert cls is not None and defaults_source(cls) == str(conf / section / "default.yaml"), section
    with pytest.raises(TnfError, match=r"^data\.batch_size: expected a whole number"):
        check_settings({"data": {"batch_size": 2.5}})
    check_settings({"data": {"batch_size": 3}, "touch": {"force": 4}})  # an integer where a number belongs is fine
    for mode in (False, True, "reduce-overhead"):  # train.compile: a switch, or torch.compile's mode by name
        check_settings({"train": {"compile": mode}})
