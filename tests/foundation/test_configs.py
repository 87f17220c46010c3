"""Every config group option composes with every stage's primary config."""

from pathlib import Path

import pytest

from tnf.cli import COMMANDS, STAGES
from tnf.env import conf_dir
from tnf.testing import compose

CONF = Path(conf_dir())
GROUPS = ["objects", "scene", "sensor", "simulator", "generator", "data", "trainer", "logger", "experiment", "debug"]
OPTIONS = [(g, p.stem) for g in GROUPS for p in sorted((CONF / g).glob("*.yaml"))]
HYDRA_STAGES = [s for s in STAGES if s not in COMMANDS]


@pytest.mark.parametrize("stage", HYDRA_STAGES)
def test_every_stage_composes(stage):
    cfg = compose(stage)
    assert cfg.seed == 0 and cfg.data_root


def test_one_primary_config_and_the_pipeline_runs_the_quickstart():
    from tnf.env import PRIMARY_CONFIG, STAGE_CHOICES

    assert sorted(p.name for p in CONF.glob("*.yaml")) == sorted(["base.yaml", f"{PRIMARY_CONFIG}.yaml", STAGE_CHOICES])
    assert compose("pipeline") == compose("touch", ["experiment=quickstart"]) != compose("touch")
    assert compose("pipeline", ["experiment=sim_digit"]) == compose("train", ["experiment=sim_digit"])
    assert compose("pipeline", ["~experiment"]) == compose("touch")


@pytest.mark.parametrize("group, option", OPTIONS, ids=[f"{g}={o}" for g, o in OPTIONS])
def test_every_group_option_composes(group, option):
    cfg = compose("pipeline", [f"{group}={option}"])
    if group not in ("experiment", "debug", "data"):
        assert cfg[group].name if "name" in cfg[group] else cfg[group]


# Options whose YAML leaves a value for the user to fill in (a path), and what a user would give.
REQUIRED = {("objects", "mesh_dir"): {"path": "/some/meshes"}, ("objects", "captured"): {"root": "/some/objects"}}


def test_component_groups_name_registered_components():
    """Each YAML of a component group names a component that validates against its Config."""
    from tnf.registry import REGISTRIES

    kinds = {"objects": "objects", "scene": "scene", "sensor": "sensor", "simulator": "simulator"}
    kinds["generator"] = "generator"
    for group, kind in kinds.items():
        for path in sorted((CONF / group).glob("*.yaml")):
            cfg = compose("pipeline", [f"{group}={path.stem}"])
            node = dict(cfg[group])
            name = node.pop("name")
            node.update(REQUIRED.get((group, path.stem), {}))
            REGISTRIES[kind].config(name, node)  # raises TnfError on unknown or mistyped keys


@pytest.mark.parametrize("experiment", sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))
def test_every_experiment_augments_only_with_what_its_sensor_has(experiment):
    """An experiment asking for the mirror augmentation or mirror-averaged generation has a sensor with a mirror
    symmetry (training would stop with an error otherwise, and generation would silently not average), and
    sim_digit's Digit, the one that asks, has it."""
    from tnf.registry import SENSORS

    cfg = compose("pipeline", [f"experiment={experiment}"])
    sensor = SENSORS.build(cfg.sensor)
    if "mirror" in cfg.data.augment:
        assert sensor.mirror_channels() is not None, f"{experiment}: {cfg.sensor.name} has no mirror symmetry"
    if cfg.generate.mirror_average:
        assert sensor.mirror_channels() is not None, f"{experiment}: {cfg.sensor.name} has no mirror symmetry"
    if experiment == "sim_digit":
        assert list(cfg.data.augment) == ["mirror"] and sensor.mirror_channels() == (1, 0, 2)
        assert cfg.generate.mirror_average


def test_the_transfer_frames_its_pairs_as_the_model_it_fine_tunes():
    """sim_omnitact_transfer fine-tunes sim_digit's T-N model: its OmniTact crops must be framed the same way
    (each as its own sensor's gel patch with crop_extent=sensor), or the pretrained encoders would see crops of
    another scale and centring. Both experiments' pair settings must also make a valid framing."""
    from tnf.data.render import Framing
    from tnf.registry import SENSORS

    framings = {}
    for experiment in ("sim_digit", "sim_omnitact_transfer"):
        cfg = compose("pipeline", [f"experiment={experiment}"])
        framing = Framing.from_settings(cfg.pair).with_sensor(SENSORS.build(cfg.sensor))
        framings[experiment] = framing
    digit, omnitact = framings["sim_digit"], framings["sim_omnitact_transfer"]
    assert digit.crop_extent == "sensor" and digit.per_view
    shared = ("crop_distance", "crop_extent", "crop_margin", "crop_px", "depth_norm", "depth_window", "render_px")
    assert {k: getattr(digit, k) for k in shared} == {k: getattr(omnitact, k) for k in shared}
    # each frames its own sensor's patch: the Digit's is portrait, OmniTact's square
    assert digit.view_size[1] > digit.view_size[0] and omnitact.view_size[0] == pytest.approx(omnitact.view_size[1])


def test_the_transfer_variants_are_the_papers_and_train_distinct_models():
    """T-N and FS fine-tune on 5 touches per training object, T-N+ on the same 5 and 45 more in all (the paper's
    "additional 45 training images"); each variant's model gets its own run id: its transfer option names it,
    and the settings its hash covers differ."""
    from tnf.generators.names import finetune_option
    from tnf.generators.settings import FinetuneSettings
    from tnf.registry import from_dict
    from tnf.stages.train import dataset_names, run_config
    from tnf.testing import hydra_job

    options, settings = {}, {}
    for variant in ("tn", "tn_plus", "fs"):
        with hydra_job("pipeline", ["experiment=sim_omnitact_transfer", f"transfer={variant}"]) as cfg:
            assert cfg.data.per_object == 5
            assert cfg.data.extra_touches == (45 if variant == "tn_plus" else 0)
            options[variant] = finetune_option("tn_cgan")
            finetune = from_dict(FinetuneSettings, cfg.finetune, where="finetune")
            datasets = dataset_names(cfg)
            settings[variant] = run_config(cfg, "finetune", finetune, datasets, source=cfg.finetune.checkpoint)
    assert all(options[v].endswith(f"+{v}") for v in options) and len(set(options.values())) == 3
    assert settings["tn"] != settings["tn_plus"] != settings["fs"] != settings["tn"]


def test_every_component_takes_its_defaults_from_its_yaml():
    """Defaults are written once, in the YAML option named like the component: its Config takes them from there
    (``@yaml_defaults``), and the option composes to exactly those values."""
    from tnf.registry import REGISTRIES, config_to_dict, defaults_source, split_spec

    checked = 0
    for kind, registry in REGISTRIES.items():
        for entry in registry.entries():
            if entry.origin != "tnf":
                continue
            cls = entry.config_class
            yaml = CONF / kind / f"{entry.name}.yaml"
            source = defaults_source(cls)
            if not yaml.is_file():  # the mesh scene, built in code, matches the capture's lights
                assert (kind, entry.name, source) == ("scene", "mesh", str(CONF / "capture" / "default.yaml"))
                continue
            assert source == str(yaml), f"{cls.__qualname__} takes its defaults from {source}, not {yaml}"
            _, params = split_spec(compose("touch", [f"{kind}={entry.name}"])[kind])
            assert config_to_dict(cls()) == params
            checked += 1
    assert checked >= 13  # every in-tree component but the mesh scene


def test_stage_settings_take_their_defaults_from_their_section():
    """The dataclasses that stage sections are validated into take their defaults from the section's YAML."""
    from tnf.capture import CaptureConfig
    from tnf.eval.classify import ClassifierConfig
    from tnf.real.calibrate import FitSettings as CalibrationFit
    from tnf.registry import config_to_dict, defaults_source, from_dict
    from tnf.scenes.system import FitSettings

    cfg = compose("touch")
    sections = {
        CaptureConfig: ("capture", cfg.capture),
        FitSettings: ("fit", cfg.fit),
        CalibrationFit: ("calibrate#fit", cfg.calibrate.fit),
        ClassifierConfig: ("evaluate#classifier", cfg.evaluate.classifier),
    }
    for cls, (section, node) in sections.items():
        folder, _, key = section.partition("#")
        expected = str(CONF / folder / "default.yaml") + (f"#{key}" if key else "")
        assert defaults_source(cls) == expected
        assert config_to_dict(from_dict(cls, node)) == config_to_dict(cls())


def test_a_sensor_config_sets_no_values_of_its_own():
    """Every sensor's values are in its YAML: the fields all sensors share have no values in the code."""
    import dataclasses

    from tnf.registry import FROM_YAML
    from tnf.sensors import SensorConfig

    assert all(
        f.default is FROM_YAML and f.default_factory is dataclasses.MISSING for f in dataclasses.fields(SensorConfig)
    )


def test_run_wide_settings_take_their_defaults_from_base_yaml():
    from omegaconf import OmegaConf

    from tnf.registry import defaults_source
    from tnf.stages.settings import RUN_ONLY, TOP_LEVEL, RunSettings

    base = OmegaConf.load(CONF / "base.yaml")
    assert defaults_source(RunSettings) == str(CONF / "base.yaml")
    fixed = [k for k in TOP_LEVEL if k != "data_root"]  # data_root's default reads TNF_DATA
    assert {k: getattr(RunSettings(), k) for k in fixed} == {k: base[k] for k in fixed}
    assert {k: base[k] for k in fixed} == {"seed": 0, "data_seed": None, "progress": True, "device": "auto"}
    assert RUN_ONLY == ("progress", "device", "data_root")  # the fields marked identity=False


def test_the_transfer_variants_start_from_the_digit_model_the_pipeline_names():
    """T-N and T-N+ name their source model by its run family (its run id without the settings hash): it must be
    the family of the run `tnf pipeline experiment=sim_digit` trains with the same seed."""
    import re

    from tnf.generators.names import HASH_CHARS
    from tnf.stages.train import model_run
    from tnf.testing import hydra_job

    with hydra_job("pipeline", ["experiment=sim_digit", "seed=2"]) as cfg:
        digit = model_run(cfg)
    for variant in ("tn", "tn_plus"):
        cfg = compose("pipeline", ["experiment=sim_omnitact_transfer", f"transfer={variant}", "seed=2"])
        assert cfg.finetune.checkpoint == "tn_cgan-digit-hashgrid-seed2"
        assert re.fullmatch(rf"{cfg.finetune.checkpoint}-[0-9a-f]{{{HASH_CHARS}}}", digit), digit


@pytest.mark.parametrize("experiment", sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))
def test_a_tiny_trial_reports_apart_from_its_experiment(experiment):
    """A trial at debug=tiny writes its own report, without the experiment's notes: its rows never join the
    experiment's report in the same store (where evaluate would refuse the experiment's own run at its end), and
    no estimate from the experiment's stage times."""
    full = compose("pipeline", [f"experiment={experiment}"])
    tiny = compose("pipeline", [f"experiment={experiment}", "debug=tiny"])
    assert tiny.evaluate.name == "tiny" != full.evaluate.name
    assert tiny.evaluate.next is None and "debug=tiny" in tiny.evaluate.notes
    assert tiny.pipeline.expected_s is None
