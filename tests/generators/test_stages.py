"""`tnf train` and `tnf finetune` on a real paired dataset (written in the tnf.data format) with the tiny config."""

import json
import logging

import numpy as np
import pytest
import torch

from tests.generators.synthetic import make_pairs
from tnf.data import SPLITS, PairWriter, write_manifest
from tnf.errors import TnfError
from tnf.generators import load_generator
from tnf.testing import compose


def to_uint8(x):
    """[-1, 1] float [N, C, H, W] -> uint8 [N, H, W, C]."""
    return ((x.clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()


def write_pairs(folder, n=12, seed=0, objects=("ball", "box")):
    """A paired dataset of the synthetic blob task at 128 px: splits cycle train, train, val."""
    p = make_pairs(n, 128, seed)
    meta = {
        "rgb": to_uint8(p["rgb"]),
        "depth": ((p["depth"][:, 0] + 1) / 2).numpy().astype(np.float16),
        "tactile": to_uint8(p["tactile"]),
        "background_index": np.zeros(n, np.int32),
        "object_id": (np.arange(n) % len(objects)).astype(np.int32),
        "split": np.array([SPLITS.index(("train", "train", "val")[i % 3]) for i in range(n)], np.int8),
        "touch_index": np.arange(n, dtype=np.int32),
        "sensor_id": np.zeros(n, np.int16),
    }
    with PairWriter(folder, n, to_uint8(p["background"][:1])) as w:
        w.write(0, **meta)
    record = {"name": "digit", "config": {}}  # the sensor record `tnf pair` writes
    write_manifest(folder, {"objects": list(objects), "sensors": ["digit"], "sensor": record, "count": n})


TINY = ["debug=tiny", "progress=false", "data.batch_size=4"]


def model_of(stage, *overrides):
    """The run id `tnf <stage> <overrides>` gives the model of its config (its generator option from Hydra)."""
    from tnf.stages.train import model_run
    from tnf.testing import hydra_job

    with hydra_job(stage, overrides) as cfg:
        return model_run(cfg)


def test_train_stage_writes_a_loadable_run(data_root, monkeypatch):
    from tnf.registry import GENERATORS
    from tnf.stages import train

    write_pairs(data_root / "pairs" / "digit-hashgrid")
    cfg = compose("train", TINY)
    checks, check = [], GENERATORS.config
    with monkeypatch.context() as m:
        m.setattr(GENERATORS, "config", lambda name, params=None: checks.append(name) or check(name, params))
        out = train.run(cfg)
    assert checks == ["tn_cgan"]  # the spec is checked once: the system builds from the stage's checked Config
    run_dir = data_root / "models" / out["run_name"]
    assert out["run_dir"] == str(run_dir) and out["run_name"].startswith("tn_cgan-digit-hashgrid-seed0-")
    for f in ("last.ckpt", "best.ckpt", "metrics.csv", "manifest.json", "grids/epoch_001.png"):
        assert (run_dir / f).is_file(), f
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["epochs"] == 2 and manifest["generator"] == "tn_cgan"
    assert manifest["datasets"] == ["digit-hashgrid"]
    system = load_generator(run_dir / "best.ckpt")
    assert system.hparams["generator"]["ngf"] == 8
    batch = {k: v for k, v in make_pairs(2, 128).items()}
    assert system.generate(batch).shape == (2, 3, 128, 128)
    # Same settings again: skipped; other settings: another run; other settings into the same run folder: refused.
    assert train.run(cfg)["skipped"]
    assert train.model_run(compose("train", [*TINY, "generator.lambda_l1=10"])) != out["run_name"]
    # The dataset rebuilt from other touches (`tnf pair` records its inputs' hash): a new run, not a skipped one.
    path = data_root / "pairs" / "digit-hashgrid" / "manifest.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "config_hash": "0123456789abcdef"}))
    again = train.run(cfg)
    assert not again.get("skipped") and again["run_name"] != out["run_name"]
    assert json.loads((data_root / "models" / again["run_name"] / "manifest.json").read_text())["config"][
        "datasets"
    ] == {"digit-hashgrid": "0123456789abcdef"}
    with pytest.raises(TnfError, match="another config"):
        named = [f"train.run_name={out['run_name']}", "train.resume=true"]
        train.run(compose("train", [*TINY, "generator.lambda_l1=10", *named]))


def test_train_stage_prints_no_lightning_advice(data_root, recwarn, caplog):
    """Lightning's notices about a non-empty run folder (tnf writes the manifest there first) and its cloud
    logger advertisement are not shown; Lightning's own start-up lines still are."""
    from tnf.stages import train

    write_pairs(data_root / "pairs" / "digit-hashgrid")
    caplog.set_level(logging.INFO)
    train.run(compose("train", TINY))
    shown = [str(w.message) for w in recwarn] + [r.getMessage() for r in caplog.records]
    assert not [m for m in shown if "exists and is not empty" in m or "litlogger" in m]
    assert any("GPU available" in r.getMessage() for r in caplog.records)


def test_pipeline_without_evaluate_names_the_earlier_report_as_not_updated(data_root, capsys):
    """A pipeline run of some stages only points at the report its experiment already has, saying that this run
    did not update it; one that evaluates names the report as its own."""
    from tnf.stages import pipeline

    write_pairs(data_root / "pairs" / "digit-hashgrid")
    cfg = compose("pipeline", [*TINY, "pipeline.stages=[train]"])
    report = data_root / "reports" / str(cfg.evaluate.name) / "report.md"
    report.parent.mkdir(parents=True)
    report.write_text("# an earlier run's report\n")
    pipeline.run(cfg)
    printed = "".join(capsys.readouterr().out.split())
    assert f"report(notupdated:evaluatedidnotrun):{report}" in printed
    assert f"report:{report}" not in printed
    assert report.read_text() == "# an earlier run's report\n"


def test_train_stage_with_the_mirror_augmentation(data_root):
    from tnf.stages import train

    write_pairs(data_root / "pairs" / "digit-hashgrid")
    with pytest.raises(TnfError, match="unknown augmentation 'flip'"):
        train.run(compose("train", [*TINY, "data.augment=[flip]"]))
    assert not (data_root / "models").exists()  # refused before anything was written
    out = train.run(compose("train", [*TINY, "data.augment=[mirror,jitter]", "train.epochs=1", "train.decay_epochs=0"]))
    manifest = json.loads((data_root / "models" / out["run_name"] / "manifest.json").read_text())
    assert manifest["epochs"] == 1 and 0 < out["last"]["val_ssim"] < 1
    assert manifest["config"]["data"]["augment"] == ["mirror", "jitter"]


def test_train_and_finetune_stages_with_a_weight_average(data_root):
    from tnf.stages import finetune, train

    write_pairs(data_root / "pairs" / "digit-hashgrid")
    write_pairs(data_root / "pairs" / "omnitact-hashgrid", n=6, seed=3)
    out = train.run(compose("train", [*TINY, "train.ema_decay=0.9", "train.epochs=1", "train.decay_epochs=0"]))
    manifest = json.loads((data_root / "models" / out["run_name"] / "manifest.json").read_text())
    assert manifest["config"]["train"]["ema_decay"] == 0.9
    state = torch.load(f"{out['run_dir']}/best.ckpt", weights_only=True)["state_dict"]
    assert int(state["ema_updates"]) == out["global_step"] > 0  # no adversarial term: one optimiser step a batch
    with pytest.raises(TnfError, match="ema_decay must be in"):
        finetune.run(compose("finetune", [*TINY, f"finetune.checkpoint={out['run_name']}", "finetune.ema_decay=2"]))
    ft = finetune.run(
        compose("finetune", [*TINY, "data.datasets=[omnitact-hashgrid]", f"finetune.checkpoint={out['run_name']}"])
    )
    ft_state = torch.load(f"{ft['run_dir']}/last.ckpt", weights_only=True)["state_dict"]
    assert not any(k.startswith("generator_ema.") for k in ft_state)  # finetune.ema_decay is its own (null)


@pytest.mark.parametrize("name", ["lee", "cyclegan"])
def test_train_stage_baselines(data_root, name):
    from tnf.stages import train

    write_pairs(data_root / "pairs" / "digit-hashgrid", n=6)
    out = train.run(compose("train", [*TINY, f"generator={name}", "train.epochs=1", "train.decay_epochs=0"]))
    assert load_generator(f"{out['run_dir']}/last.ckpt").generator_name == name


def test_finetune_stage_from_checkpoint_and_from_scratch(data_root):
    from tnf.stages import finetune, train

    write_pairs(data_root / "pairs" / "digit-hashgrid")
    write_pairs(data_root / "pairs" / "omnitact-hashgrid", n=6, seed=3)
    train.run(compose("train", TINY))
    src = data_root / "models" / train.model_run(compose("train", TINY)) / "best.ckpt"
    src_bytes = src.read_bytes()
    ft = [*TINY, "data.datasets=[omnitact-hashgrid]"]
    # The source named by its run family: the one finished run of that generator, dataset and seed.
    frozen = ["finetune.checkpoint=tn_cgan-digit-hashgrid-seed0", "finetune.freeze=[net_g.encoders.rgb]"]
    out = finetune.run(compose("finetune", [*ft, *frozen]))
    assert out["run_name"].startswith("tn_cgan+ft-omnitact-hashgrid-seed0-")
    assert src.read_bytes() == src_bytes
    a = torch.load(src, weights_only=True)["state_dict"]
    b = torch.load(f"{out['run_dir']}/last.ckpt", weights_only=True)["state_dict"]
    rgb = [k for k in a if k.startswith("generator.net_g.encoders.rgb.") and k.endswith("weight")]
    bg = [k for k in a if k.startswith("generator.net_g.encoders.background.") and k.endswith("weight")]
    assert rgb and all(torch.equal(a[k], b[k]) for k in rgb)
    assert any(not torch.equal(a[k], b[k]) for k in bg)
    manifest = json.loads((data_root / "models" / out["run_dir"].split("/")[-1] / "manifest.json").read_text())
    assert manifest["source"]["checkpoint"] == str(src.resolve()) and manifest["frozen"]

    scratch = finetune.run(compose("finetune", ft))
    assert scratch["run_name"].startswith("tn_cgan+ft-omnitact-hashgrid-seed0-")
    assert scratch["run_name"] != out["run_name"]
    c = torch.load(f"{scratch['run_dir']}/last.ckpt", weights_only=True)["state_dict"]
    assert not torch.equal(a[rgb[0]], c[rgb[0]])

    with pytest.raises(TnfError, match="finetune.checkpoint"):
        finetune.run(compose("finetune", [*ft, "finetune.checkpoint=nope"]))
    # A finished fine-tune whose best.ckpt is gone is fine-tuned again, not skipped.
    assert finetune.run(compose("finetune", ft)).get("skipped")
    (data_root / "models" / scratch["run_name"] / "best.ckpt").unlink()
    again = finetune.run(compose("finetune", ft))
    assert not again.get("skipped") and (data_root / "models" / scratch["run_name"] / "best.ckpt").is_file()


def test_finetune_on_per_object_touches_and_extra_ones_records_its_pairs(data_root, capsys):
    """T-N+'s fine-tuning set: data.per_object touches of each object and data.extra_touches more; the run's
    manifest and its summary line say how many pairs it trained on."""
    from tnf.stages import finetune

    write_pairs(data_root / "pairs" / "omnitact-hashgrid", n=6, seed=3)  # 4 training touches, 2 per object
    ft = [*TINY, "data.datasets=[omnitact-hashgrid]", "data.per_object=1"]
    for extra, pairs in ((0, 2), (1, 3)):
        out = finetune.run(compose("finetune", [*ft, f"data.extra_touches={extra}", f"finetune.run_name=ft{extra}"]))
        assert json.loads((data_root / "models" / f"ft{extra}" / "manifest.json").read_text())["train_pairs"] == pairs
        assert out["train_pairs"] == pairs
        assert f"epochs on {pairs} pairs" in capsys.readouterr().out


def test_finetune_writes_last_ckpt_after_the_last_epoch_between_validations(data_root):
    """Three epochs validated every second one: last.ckpt, which the press realism scores, is the third epoch's."""
    from tnf.generators.training import _progress
    from tnf.stages import finetune

    write_pairs(data_root / "pairs" / "omnitact-hashgrid", n=6, seed=3)
    ft = [*TINY, "data.datasets=[omnitact-hashgrid]", "finetune.epochs=3", "finetune.val_every_n_epochs=2"]
    out = finetune.run(compose("finetune", ft))
    assert out["epochs"] == 3
    assert _progress(data_root / "models" / out["run_name"] / "last.ckpt", "val_l1")[0] == 3


@pytest.mark.parametrize("name", ["tn_cgan", "lee", "cyclegan"])
def test_generator_config_files_match_the_config_classes(name):
    """conf/generator/<name>.yaml and the generator's Config hold the same defaults, so that `tnf train` and
    building a generator in Python (a test, a notebook) train the same network with the same loss."""
    import dataclasses

    from omegaconf import OmegaConf

    from tnf.registry import GENERATORS

    composed = OmegaConf.to_container(compose("train", [f"generator={name}"]).generator, resolve=True)
    assert isinstance(composed, dict) and composed.pop("name") == name
    fields = dataclasses.fields(GENERATORS.get(name).Config)
    defaults = {f.name: f.default if f.default is not dataclasses.MISSING else f.default_factory() for f in fields}
    assert composed == defaults


def test_train_stops_at_a_plateau(data_root):
    """train.patience stops a run once validation SSIM stops rising; the run id holds it, the manifest says where
    it stopped, and last.ckpt is that epoch's and holds the plateau's count (what a resumed run counts on)."""
    from tnf.generators.training import _progress
    from tnf.stages import train

    write_pairs(data_root / "pairs" / "digit-hashgrid")
    base = [*TINY, "train.epochs=6", "train.decay_epochs=0", "train.checkpoint_every_s=0"]
    # No rise counts as one (min_delta 1): the first validation sets the best, the next two do not beat it.
    plateau = [*base, "train.patience=2", "train.min_delta=1.0"]
    assert model_of("train", *plateau) != model_of("train", *base)
    assert model_of("train", *base, "train.min_delta=0.5") == model_of("train", *base)  # no patience: no part
    out = train.run(compose("train", plateau))
    run_dir = data_root / "models" / out["run_name"]
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["epochs"] == 3 and _progress(run_dir / "last.ckpt", "val_l1")[0] == 3
    assert manifest["plateau"] == {"patience": 2, "min_delta": 1.0, "stopped": True}
    ckpt = torch.load(run_dir / "last.ckpt", map_location="cpu", weights_only=False)
    states = [s for k, s in ckpt["callbacks"].items() if k.startswith("EarlyStopping")]
    assert len(states) == 1 and states[0]["wait_count"] == 2
    # What the evaluation report shows of it: the validation curve and the plateau.
    from tnf.eval.run import training_record

    record = training_record(run_dir, manifest)
    assert [e for e, _ in record["val_curve"]] == [1, 2, 3] and all(0 < s < 1 for _, s in record["val_curve"])
    assert record["val_curve"][-1][1] == pytest.approx(manifest["last"]["val_ssim"], abs=1e-6)
    assert record["plateau"] == {"patience": 2, "min_delta": 1.0, "stopped": True, "epochs": 3}
    assert "unfinished" not in record
    # A run folder without a manifest (training cut short) says so.
    assert training_record(run_dir, None)["unfinished"] is True
    # A row that does not parse is left out with a warning; the evaluation does not stop for the curve.
    text = (run_dir / "metrics.csv").read_text()
    last = str(manifest["last"]["val_ssim"])[:6]
    assert last in text
    (run_dir / "metrics.csv").write_text(text.replace(last, "oops", 1))
    assert [e for e, _ in training_record(run_dir, manifest)["val_curve"]] == [1, 2]
    # A patient run that never stalls trains every epoch and says so.
    out = train.run(compose("train", [*base, "train.patience=50"]))
    manifest = json.loads((data_root / "models" / out["run_name"] / "manifest.json").read_text())
    assert manifest["epochs"] == 6 and manifest["plateau"]["stopped"] is False
    with pytest.raises(TnfError, match="patience"):
        train.run(compose("train", [*base, "train.patience=0"]))
