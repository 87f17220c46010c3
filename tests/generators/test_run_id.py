"""One run id per model: `tnf train`, `tnf pipeline` and `tnf generate` name the model of a config the same way
(tnf.generators.names): generator option, dataset, seed and the hash of the settings that define the model."""

import json
import os
import subprocess
import sys

import pytest

from tests.generators.test_stages import TINY, write_pairs
from tnf.errors import TnfError
from tnf.generators.names import HASH_CHARS, find_run
from tnf.testing import compose, hydra_job

# The quick start's settings at the tiny size.
SETTINGS = ["experiment=quickstart", *TINY]


def tnf(*args, root):
    env = {**os.environ, "TNF_DATA": str(root), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-m", "tnf.cli", *args], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out


def test_a_pipeline_after_tnf_train_with_the_same_settings_reuses_its_model(data_root):
    write_pairs(data_root / "pairs" / "digit-hashgrid")
    tnf("train", *SETTINGS, root=data_root)
    (run,) = (data_root / "models").iterdir()
    # The quick start's generator option (a variant of tn_cgan), the dataset, the seed and the settings hash.
    manifest = json.loads((run / "manifest.json").read_text())
    assert run.name == f"tn_cgan_press-digit-hashgrid-seed0-{manifest['config_hash'][:HASH_CHARS]}"
    files = {p: p.stat().st_mtime_ns for p in run.rglob("*")}
    ckpt = (run / "last.ckpt").read_bytes()

    out = tnf("pipeline", *SETTINGS, "pipeline.stages=[train]", root=data_root)
    assert f"{run.name}: trained with the same settings, skipped" in " ".join(out.stdout.split())
    assert [p.name for p in (data_root / "models").iterdir()] == [run.name]  # no second run folder
    assert {p: p.stat().st_mtime_ns for p in run.rglob("*")} == files  # nothing in it rewritten
    assert (run / "last.ckpt").read_bytes() == ckpt
    timings = json.loads((data_root / "reports" / "tiny" / "timings" / f"{run.name}.json").read_text())
    assert timings["model"] == run.name


def test_the_run_id_names_the_generator_option_and_agrees_with_the_skip_key(data_root):
    from tnf.stages import train

    write_pairs(data_root / "pairs" / "digit-hashgrid", n=6)
    short = ["train.epochs=1", "train.decay_epochs=0"]
    out = train.run(compose("train", [*TINY, *short]))
    manifest = json.loads((data_root / "models" / out["run_name"] / "manifest.json").read_text())
    # Composed without a Hydra job: the registered name; the hash is the one the manifest records.
    assert out["run_name"] == f"tn_cgan-digit-hashgrid-seed0-{manifest['config_hash'][:HASH_CHARS]}"
    with hydra_job("train", [*TINY, *short]) as cfg:
        assert train.model_run(cfg) == out["run_name"]  # the option is tn_cgan's own
    with hydra_job("train", [*TINY, *short, "generator=tn_cgan_plain"]) as cfg:
        assert train.model_run(cfg).startswith("tn_cgan_plain-digit-hashgrid-seed0-")
    # Another seed or setting: another run; train.run_name replaces the id.
    assert train.model_run(compose("train", [*TINY, *short, "seed=1"])).startswith("tn_cgan-digit-hashgrid-seed1-")
    assert train.model_run(compose("train", [*TINY, "train.epochs=3"])) != out["run_name"]
    assert train.model_run(compose("train", [*TINY, "train.run_name=mine"])) == "mine"
    # Settings that do not change the model keep the id.
    unhashed = ["train.force=true", "train.compile=true", "train.checkpoint_every_s=5"]
    assert train.model_run(compose("train", [*TINY, *short, *unhashed])) == out["run_name"]


def test_a_run_family_names_its_one_finished_run(data_root):
    models = data_root / "models"
    assert find_run(models, "tn_cgan-digit-hashgrid-seed0") is None
    (models / "tn_cgan-digit-hashgrid-seed0-0123abcd").mkdir(parents=True)  # unfinished: no manifest
    (models / "tn_cgan-digit-hashgrid-seed0-extra-0123abcd").mkdir()  # another family
    assert find_run(models, "tn_cgan-digit-hashgrid-seed0") is None
    (models / "tn_cgan-digit-hashgrid-seed0-0123abcd" / "manifest.json").write_text("{}")
    (models / "tn_cgan-digit-hashgrid-seed0-extra-0123abcd" / "manifest.json").write_text("{}")
    assert find_run(models, "tn_cgan-digit-hashgrid-seed0") == "tn_cgan-digit-hashgrid-seed0-0123abcd"
    assert find_run(models, "tn_cgan-digit-hashgrid-seed0-0123abcd") == "tn_cgan-digit-hashgrid-seed0-0123abcd"
    (models / "tn_cgan-digit-hashgrid-seed0-4567cdef").mkdir()
    (models / "tn_cgan-digit-hashgrid-seed0-4567cdef" / "manifest.json").write_text("{}")
    with pytest.raises(TnfError, match="several finished runs.*0123abcd, .*4567cdef"):
        find_run(models, "tn_cgan-digit-hashgrid-seed0")


def test_settings_diff_names_the_dotted_keys_that_differ():
    from tnf.generators.names import settings_diff

    old = {"generator": {"ngf": 8, "ndf": 8, "name": "tn_cgan"}, "train": {"epochs": 2, "lr": 0.001}, "seed": 0}
    new = {"generator": {"ngf": 16, "ndf": 8, "name": "lee"}, "train": {"epochs": 2, "ema": 0.9}, "seed": 0}
    assert settings_diff(old, old) == ""
    assert settings_diff(old, new) == (
        'generator.name: "tn_cgan" -> "lee"; generator.ngf: 8 -> 16; train.ema: unset -> 0.9; train.lr: 0.001 -> unset'
    )
    assert settings_diff(old, {**new, "seed": 1, "data": {"size": [64, 64]}}) == (
        'data.size: unset -> [64, 64]; generator.name: "tn_cgan" -> "lee"; generator.ngf: 8 -> 16; '
        "seed: 0 -> 1; and 2 more"
    )


def test_a_new_run_names_the_settings_that_differ_from_the_latest_run_of_its_family(data_root, capsys):
    from tests.reliability.helpers import run_tnf
    from tnf.cli import main

    write_pairs(data_root / "pairs" / "digit-hashgrid")
    assert run_tnf(capsys, "train", *SETTINGS)[0] == 0
    (old,) = (data_root / "models").iterdir()
    (data_root / "models" / f"{old.name[:-HASH_CHARS]}0123abcd").mkdir()
    (data_root / "models" / f"{old.name[:-HASH_CHARS]}0123abcd" / "run.json").write_text("{")  # malformed: passed over
    capsys.readouterr()
    assert main(["train", *SETTINGS, "generator.ngf=16"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("a new run:")]
    assert lines == [f"a new run: {old.name} has other settings (generator.ngf: 8 -> 16)"]


@pytest.mark.parametrize(("flags", "expected"), [({"avx512_bf16", "avx2"}, "bf16-mixed"), ({"avx2"}, "32-true")])
def test_precision_auto_trains_in_bf16_only_on_cpus_that_run_it_natively(data_root, monkeypatch, flags, expected):
    from tnf import runtime
    from tnf.stages import train

    monkeypatch.setattr(runtime, "cpu_flags", lambda: frozenset(flags))
    write_pairs(data_root / "pairs" / "digit-hashgrid", n=6)
    short = ["train.epochs=1", "train.decay_epochs=0"]
    out = train.run(compose("train", [*TINY, *short, "trainer.precision=auto"]))
    manifest = json.loads((data_root / "models" / out["run_name"] / "manifest.json").read_text())
    assert manifest["precision"] == expected  # what the trainer ran in
    # The run is identified by the precision it trains in, not by "auto".
    assert out["run_name"] == train.model_run(compose("train", [*TINY, *short, f"trainer.precision={expected}"]))
    # Other values pass through.
    assert runtime.resolve_precision("32-true", "cpu") == "32-true"
    assert runtime.resolve_precision("bf16-mixed", "cpu") == "bf16-mixed"


def test_cpu_flags_are_read_from_the_machine():
    from pathlib import Path

    from tnf.runtime import cpu_flags

    if not Path("/proc/cpuinfo").is_file():
        pytest.skip("no /proc/cpuinfo")
    flags = cpu_flags()
    assert flags and all(" " not in f for f in flags)


def test_a_run_another_process_is_training_is_refused_at_once(data_root, capsys):
    """Two processes training one run id would write one folder's checkpoints and metrics.csv at once."""
    import fcntl

    from tests.reliability.helpers import run_tnf

    write_pairs(data_root / "pairs" / "digit-hashgrid")
    assert run_tnf(capsys, "train", *SETTINGS)[0] == 0
    (run,) = (data_root / "models").iterdir()
    ckpt = (run / "last.ckpt").read_bytes()
    with open(run / ".lock", "a") as other:  # as the other process holds it
        fcntl.flock(other.fileno(), fcntl.LOCK_EX)
        rc, err = run_tnf(capsys, "train", *SETTINGS, "train.force=true")
    assert rc == 1 and err.startswith(f"error: another process is training {run.name}"), err
    assert (run / "last.ckpt").read_bytes() == ckpt  # its folder untouched
