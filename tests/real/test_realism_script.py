"""experiments/real_realism.py's choices that hold before any run: the split of each taxim recording, and that
taxim's other recording (the check that the procedure carries over) fits the sensor the script simulates."""

import importlib.util
from pathlib import Path

import pytest

from tnf.real.presses import at_sensor_size, import_taxim
from tnf.registry import SENSORS

ROOT = Path(__file__).resolve().parents[2]


def _script():
    spec = importlib.util.spec_from_file_location("real_realism", ROOT / "experiments" / "real_realism.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_recording_splits_by_the_minis_rule():
    script = _script()
    conf = ROOT / "conf"
    mini = script.split("gelsight_mini", 24, conf)
    assert mini == (list(range(16)), list(range(16, 24)))  # conf/calibrate/default.yaml
    assert script.split("gelsight", 24, conf) == mini  # the rule, on the Mini's count, gives the Mini's split
    assert script.split("gelsight", 48, conf) == (list(range(32)), list(range(32, 48)))
    assert set(script.RECORDINGS) == {"gelsight_mini", "gelsight"}
    assert script.calibration_name("gelsight_mini", 160, 120) == "mini_160x120"  # the experiment's own name
    assert script.calibration_name("gelsight", 160, 120) == "gelsight_160x120"
    assert script.calibration_name("gelsight_mini", 320, 240) == "mini_320x240"  # sim_gelsight_mini_gpu's


@pytest.mark.parametrize(
    ("experiment", "size", "family", "gpu_precision"),
    [
        # The CPU experiment's own precision, auto (bf16-mixed where the device runs it), beats trainer=gpu's.
        ("sim_gelsight_mini", (160, 120), "tn_cgan_plain-gelsight_mini-hashgrid-seed3", "auto"),
        ("sim_gelsight_mini_gpu", (320, 240), "tn_cgan-gelsight_mini-hashgrid-seed3", "bf16-mixed"),
    ],
)
def test_the_script_finds_each_experiments_model_and_calibration(experiment, size, family, gpu_precision):
    """The model the script looks for is the one `tnf pipeline` names, at the calibration's size."""
    from tnf.stages.train import model_run
    from tnf.testing.config import hydra_job

    script = _script()
    got = script.pipeline_settings(experiment, 3, [])
    assert (got["width"], got["height"]) == size
    assert got["trainer"]["accelerator"] == "cpu"
    on_gpu = script.pipeline_settings(experiment, 3, ["trainer=gpu", "sensor.width=80", "sensor.height=60"])
    assert (on_gpu["width"], on_gpu["height"]) == (80, 60)
    assert on_gpu["trainer"]["accelerator"] == "gpu" and on_gpu["trainer"]["precision"] == gpu_precision
    # The model is the run the pipeline's own settings name, in the script's data root.
    args = script.pipeline_args(Path("/data"), 3, "gelsight_mini", [0, 1], [2], experiment, ["trainer=gpu"], size)
    assert args[:3] == [f"experiment={experiment}", "data_root=/data", "seed=3"] and args[-1] == "trainer=gpu"
    with hydra_job("pipeline", args) as cfg:
        assert model_run(cfg).startswith(family + "-")
    other = script.pipeline_args(Path("/data"), 3, "gelsight", list(range(32)), [32], experiment, [], size)
    assert "calibrate.presses=taxim:gelsight" in other and f"calibrate.name=gelsight_{size[0]}x{size[1]}" in other


def test_a_data_root_rebuilt_with_other_touches_names_another_model(tmp_path):
    """The script scores the run the pipeline's settings and the data root's pairs name: pairs rebuilt from other
    touches (another touch setting on a reused --data-root) name a new model, not the one already there."""
    import json

    from tnf.stages.train import dataset_names, model_run
    from tnf.testing.config import hydra_job

    script = _script()
    args = script.pipeline_args(tmp_path, 0, "gelsight_mini", [0], [1], "sim_gelsight_mini", [], (160, 120))
    names = []
    for key in ("0" * 16, "1" * 16):
        with hydra_job("pipeline", args) as cfg:
            pairs = tmp_path / "pairs" / dataset_names(cfg)[0]
            pairs.mkdir(parents=True, exist_ok=True)
            (pairs / "manifest.json").write_text(json.dumps({"config_hash": key}))
            names.append(model_run(cfg))
    assert names[0] != names[1]
    assert all(n.startswith("tn_cgan_plain-gelsight_mini-hashgrid-seed0-") for n in names)


def test_the_cpu_experiment_fine_tunes_in_its_own_precision():
    assert _script().pipeline_settings("sim_gelsight_mini", 0, [])["trainer"]["precision"] == "auto"


def test_taxims_gelsight_recording_fits_the_minis_geometry(tmp_path):
    presses = import_taxim("gelsight", tmp_path / "presses")
    assert len(presses) == 48 and (presses.width, presses.height) == (640, 480)
    for size in ((320, 240), (160, 120)):  # the script's calibration, and the pipeline's
        sensor = SENSORS.build({"name": "gelsight_mini", "width": size[0], "height": size[1]})
        sp = at_sensor_size(presses, sensor, list(range(48)))
        assert sp.frames.shape == (48, size[1], size[0], 3)


def test_a_data_root_holds_one_recording(tmp_path):
    script = _script()
    root = tmp_path / "root"
    script.claim_root(root, "gelsight")
    script.claim_root(root, "gelsight")  # the same recording again: its runs are reused
    with pytest.raises(SystemExit, match="holds the runs of the gelsight recording; give another for --recording"):
        script.claim_root(root, "gelsight_mini")
    assert (root / "realism_recording.txt").read_text() == "gelsight\n"  # left as it was
    # A root written before the marker, with the pipeline's T-N in it: the Mini's.
    old = tmp_path / "old"
    (old / "models" / "tn_cgan_plain-gelsight_mini-hashgrid-seed0-0123abcd").mkdir(parents=True)
    with pytest.raises(SystemExit, match="holds the runs of the gelsight_mini recording"):
        script.claim_root(old, "gelsight")
    script.claim_root(old, "gelsight_mini")


def test_a_wrong_pipeline_setting_is_one_line_before_anything_is_written():
    script = _script()
    with pytest.raises(SystemExit, match="experiment=nosuch: no such experiment"):
        script.pipeline_settings("nosuch", 0, [])
    with pytest.raises(SystemExit, match="fit.stepz: no such setting"):
        script.pipeline_settings("sim_gelsight_mini_gpu", 0, ["fit.stepz=3"])


def test_the_cpu_experiment_presses_as_shallow_as_the_real_presses():
    """sim_gelsight_mini draws each touch's force from 0.2-3 N (docs/decisions/real_press_depths.md): a plan the
    GelSight Mini accepts, whose training forces span the range outside the held-out band."""
    import numpy as np

    from tnf.sim.forces import force_plan
    from tnf.testing.config import hydra_job

    with hydra_job("pipeline", ["experiment=sim_gelsight_mini"]) as cfg:
        sensor = SENSORS.build(dict(cfg.sensor))
        plan = force_plan(cfg.touch.force_range, sensor)
    assert plan is not None and (plan.min, plan.max, plan.dist) == (0.2, 3.0, "log_uniform")
    forces = plan.training_forces(np.random.default_rng(0), 2000)
    assert forces.min() >= 0.2 and forces.max() <= 3.0
    assert not ((forces > 2.6) & (forces < 2.8)).any()  # the held-out band, above every real press's depth
    assert (forces < 0.5).mean() > 0.3  # log-uniform: the shallow presses are not rare
    sensor.check_force(plan.extrapolation[1])  # the novel-view band stays within the sensor's force range
