import subprocess
import sys
import types

import pytest

from tnf import TnfError
from tnf.cli import STAGES, main


def run_cli(*args, env=None):
    return subprocess.run([sys.executable, "-m", "tnf.cli", *args], capture_output=True, text=True, env=env)


def test_help_lists_every_stage():
    out = run_cli("--help")
    assert out.returncode == 0
    for stage in STAGES:
        assert stage in out.stdout


def test_unknown_stage_is_one_clear_line():
    out = run_cli("frobnicate")
    assert out.returncode == 1
    assert out.stderr.strip().splitlines() == [
        "error: unknown stage 'frobnicate'; stages: " + ", ".join(STAGES) + " (see tnf --help)"
    ]


@pytest.fixture
def echo_stage(monkeypatch):
    """Stand in for the `objects` stage's code (the real stage config is used)."""
    seen = {}

    def run(cfg):
        seen["cfg"] = cfg
        if cfg.seed == 13:
            raise TnfError("seed 13 is unlucky")

    module = types.ModuleType("tnf.stages.objects")
    module.run = run
    monkeypatch.setitem(sys.modules, "tnf.stages.objects", module)
    return seen


def test_stage_gets_composed_config_with_overrides(echo_stage, data_root):
    assert main(["objects", "seed=7", "trainer=gpu", "debug=tiny"]) == 0
    cfg = echo_stage["cfg"]
    assert cfg.seed == 7 and cfg.trainer.accelerator == "gpu" and list(cfg.object_names) == ["ball", "box"]
    assert cfg.data_root == str(data_root)


def test_every_stage_logs_to_its_own_folder(echo_stage, data_root):
    assert main(["objects"]) == 0
    assert main(["objects", "-m", "seed=1,2"]) == 0
    assert sorted(p.name for p in (data_root / "logs" / "stage").iterdir()) == ["objects", "objects-multirun"]
    assert list((data_root / "logs" / "stage" / "objects").glob("*/objects.log"))


def test_hydra_gets_the_job_name_and_stage_defaults_beside_the_overrides():
    from tnf.cli import _hydra_args

    assert _hydra_args("pipeline", ["-m", "seed=1,2"]) == [
        "hydra.job.name=pipeline",
        "experiment=quickstart",
        "seed=1,2",
        "-m",
    ]
    assert _hydra_args("pipeline", ["experiment=sim_digit"]) == ["hydra.job.name=pipeline", "experiment=sim_digit"]
    assert _hydra_args("fit-scene", ["--cfg=job", "--info"]) == ["hydra.job.name=fit_scene", "--cfg=job", "--info"]
    # Overrides on both sides of a flag (the README's sweep) become one run of overrides.
    assert _hydra_args("train", ["experiment=sim_digit", "-m", "generator=lee,cyclegan", "--cfg", "job"]) == [
        "hydra.job.name=train",
        "experiment=sim_digit",
        "generator=lee,cyclegan",
        "-m",
        "--cfg",
        "job",
    ]


def test_overrides_before_and_after_multirun_sweep(data_root, capsys):
    """``tnf STAGE a=1 -m b=2,3`` (the README's GPU sweep) runs the sweep; Hydra's parser alone refuses it."""
    assert main(["objects", "object_names=[ball]", "-m", "seed=1,2"]) == 0
    runs = sorted((data_root / "logs" / "stage" / "objects-multirun").glob("*/*"))
    assert [p.name for p in runs if p.is_dir()] == ["0", "1"]


def test_stage_user_error_exits_nonzero_with_one_line(echo_stage, data_root, capsys):
    assert main(["objects", "seed=13"]) == 1
    err = capsys.readouterr().err
    assert "error: seed 13 is unlucky" in err and "Traceback" not in err


def test_bad_override_is_an_error(echo_stage, data_root, capsys):
    assert main(["objects", "sensor=no_such_sensor"]) != 0
    assert "no_such_sensor" in capsys.readouterr().err


def test_multirun_runs_each_job(echo_stage, data_root):
    seeds = []
    sys.modules["tnf.stages.objects"].run = lambda cfg: seeds.append(cfg.seed)
    assert main(["objects", "-m", "seed=1,2,3"]) == 0
    assert seeds == [1, 2, 3]


@pytest.mark.parametrize(
    "override, expected",
    [
        ("generator=foo", "error: generator=foo: no such generator; options: cyclegan, lee, tn_cgan"),
        (
            "sensor=gelsigth_mini",
            "error: sensor=gelsigth_mini: no such sensor (did you mean sensor=gelsight_mini?); options: digit",
        ),
        ("trian.epochs=1", "error: trian.epochs: no such setting; did you mean train.epochs?"),
        ("sensor.widht=3", "error: sensor.widht: no such setting; did you mean sensor.width?"),
        (
            "train.epochs=1,2",
            "error: Ambiguous value for argument 'train.epochs=1,2' 1. To use it as a list, use key=[v",
        ),
        # The keys of the generator chosen, not of the default one
        (
            "generator=cyclegan generator.lambda_cycl=3",
            "error: generator.lambda_cycl: no such setting; did you mean generator.lambda_cycle?",
        ),
        # No near key: no guess from another key's section prefix, and no "+key" advice that the section refuses
        ("sensor.marker_flw=1", "error: sensor.marker_flw: no such setting; see `tnf train --cfg job` for the"),
        ("object_names=[größe]", "error: object_names=[größe]: cannot be read; quote a value with spaces or non-ASCII"),
    ],
)
def test_hydra_config_errors_are_one_line(override, expected, capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    assert main(["train", *override.split(" ")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(expected), err
    assert "+sensor" not in err[0]
    assert not (tmp_path / "logs").exists()  # refused before Hydra made its run folder


def test_a_registered_option_without_its_yaml_names_the_conf_entry_point(capsys, tmp_path, monkeypatch):
    """A plugin that forgot its tnf.conf entry point: `tnf list` shows its sensor, and `sensor=NAME` says why it
    cannot be chosen rather than that there is no such sensor."""
    from tnf.registry import SENSORS, Entry

    SENSORS.names()  # discovered: the entry below joins them
    monkeypatch.setitem(SENSORS._entries, "tiny", Entry("tiny", object, "tnf-tiny"))
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    assert main(["train", "sensor=tiny"]) == 1
    assert (
        capsys.readouterr()
        .err.strip()
        .startswith(
            "error: sensor=tiny: sensor 'tiny' is registered by tnf-tiny but has no sensor/tiny.yaml; tnf-tiny needs a "
            "tnf.conf entry point naming the package of its YAML files (docs/plugins.md); options: digit"
        )
    )


def test_list_names_the_option_that_chooses_each_component(monkeypatch):
    """`tnf list`'s option column: `kind=name` for a config group option, the setting a class names for one built in
    code (the mesh scene), and the missing YAML for a plugin that forgot its tnf.conf entry point."""
    from tnf.listing import component_rows
    from tnf.registry import SENSORS, Entry

    SENSORS.names()
    monkeypatch.setitem(SENSORS._entries, "tiny", Entry("tiny", object, "tnf-tiny"))
    option = {(kind, name): choose for kind, name, _, choose, _ in component_rows()}
    assert option[("scene", "hashgrid")] == "scene=hashgrid"
    assert option[("generator", "tn_cgan")] == "generator=tn_cgan"
    assert option[("objects", "mesh_dir")] == "objects=mesh_dir"
    assert option[("scene", "mesh")] == "pair.scene_source=mesh"
    assert option[("sensor", "tiny")] == "none: no sensor/tiny.yaml"


@pytest.mark.parametrize(
    "sweep, expected",
    [
        (["generator=tn_cgan,foo", "seed=0,1"], "error: generator=foo: no such generator; options: cyclegan"),
        (["train.epochs=1,-2"], "error: train.epochs: must be >= 0, got -2"),
    ],
)
def test_a_sweep_with_one_bad_value_is_one_line_before_any_job(sweep, expected, capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    assert main(["train", "-m", *sweep]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(expected), err
    assert not (tmp_path / "logs").exists()


def test_printed_paths_are_not_wrapped_at_the_console_width(tmp_path):
    import os

    # Output to a pipe is 80 columns wide: a long data root's paths must still print whole, on one line.
    root = tmp_path / ("a-long-folder-name-" * 4) / "tnf-data"
    env = {**os.environ, "COLUMNS": "80", "OMP_NUM_THREADS": "1"}
    args = ("capture", "debug=tiny", "progress=false", "object_names=[ball]", "capture.num_views=2")
    out = run_cli(*args, "capture.num_test_views=1", f"data_root={root}", env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    folder = root / "capture" / "builtin"
    assert any(f"capture -> {folder}" in line for line in out.stdout.splitlines()), out.stdout


def test_output_to_a_reader_that_has_gone_ends_quietly(tmp_path):
    """`tnf train --help | head`: the pipe's reader exits first; no traceback, the exit code of a broken pipe."""
    import os

    r, w = os.pipe()
    os.close(r)  # every write to w fails: the reader has gone
    env = {**os.environ, "TNF_DATA": str(tmp_path)}
    try:
        out = subprocess.run(
            [sys.executable, "-m", "tnf.cli", "train", "--help"], stdout=w, stderr=subprocess.PIPE, env=env, timeout=120
        )
    finally:
        os.close(w)
    assert out.returncode == 141 and "Traceback" not in out.stderr.decode() and not out.stderr.strip(), out.stderr


def test_a_bad_generator_setting_is_refused_before_any_stage(data_root, capsys):
    """The pipeline builds the generator after hours of data stages, and a sweep's first jobs run before a later
    job's values are read: a value its Config refuses stops the command before any work."""
    assert main(["pipeline", "debug=tiny", "generator=lee", "generator.norm=bogus"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: generator.lee: norm must be batch, instance or none, got 'bogus'"]
    assert main(["train", "debug=tiny", "-m", "generator.ngf=4,0"]) == 1
    assert "generator.tn_cgan: ngf and ndf must be >= 1, got 0" in capsys.readouterr().err
    assert not (data_root / "capture").exists() and not (data_root / "models").exists()


def test_a_sweep_with_cfg_is_one_line(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    assert main(["objects", "-m", "seed=1,2", "--cfg", "job"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: Only one of --run, --multirun") and "give one of them" in err[0]


def test_printing_the_config_checks_the_overrides_as_a_run_does(capsys, tmp_path, monkeypatch):
    monkeypatch.setenv("TNF_DATA", str(tmp_path))
    assert main(["train", "trian.epochs=1", "--cfg", "job"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: trian.epochs: no such setting; did you mean train.epochs?"]
    assert main(["train", "train.epochs=3", "--cfg", "job"]) == 0
    assert "epochs: 3" in capsys.readouterr().out
    # and leaves no Hydra job behind that later code in this process would take for its own
    from hydra.core.hydra_config import HydraConfig

    assert not HydraConfig.initialized()
