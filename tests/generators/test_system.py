"""GeneratorSystem with Lightning and its callbacks: a tiny training run, checkpoints, loading, resume, NaN
guard, weight average, discriminator watch, image grids, fine-tuning."""

import csv
import hashlib
import json

import pytest
import torch

from tests.generators.synthetic import SyntheticPairs, make_pairs
from tnf.data import mirror_batch
from tnf.errors import NonFiniteLoss, TnfError
from tnf.generators import GeneratorSystem, load_generator
from tnf.generators.callbacks import (
    DiscriminatorWatch,
    ImageGrids,
    WeightAverage,
    build_callbacks,
    discriminator_saturated,
    image_grid,
)
from tnf.generators.system import generator_config, generator_spec
from tnf.generators.training import fit, keep_epochs

# With the adversarial term (not the default), so that both players' optimisers, schedules and logs are exercised.
SPEC = {"name": "tn_cgan", "image_size": 32, "ngf": 4, "ndf": 4, "dropout_at_generation": False, "lambda_gan": 1.0}
CPU = {"accelerator": "cpu", "devices": 1, "precision": "32-true"}


def train(run_dir, epochs=2, dm=None, system=None, resume=True, checkpoint_every_s=0.0, callbacks=None, **kw):
    torch.manual_seed(0)
    system = system or GeneratorSystem(SPEC, epochs=epochs, decay_epochs=1, grid_rows=3, finite_check_every=1)
    dm = dm or SyntheticPairs(n_train=8, n_val=4, size=32, batch_size=4)
    summary = fit(
        system,
        dm,
        run_dir,
        config={"spec": SPEC, "epochs": epochs, **kw},
        trainer_cfg=CPU,
        callbacks=callbacks,
        progress=False,
        resume=resume,
        log_every_n_steps=1,
        checkpoint_every_s=checkpoint_every_s,
    )
    return system, summary


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("models") / "run"
    system, summary = train(run_dir, epochs=2)
    return run_dir, system, summary


def test_run_folder(trained):
    run_dir, system, summary = trained
    for f in ("last.ckpt", "best.ckpt", "metrics.csv", "manifest.json", "grids/epoch_000.png", "grids/epoch_001.png"):
        assert (run_dir / f).is_file(), f
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["epochs"] == 2 and 0 < manifest["best_val_l1"] <= 2
    csv = (run_dir / "metrics.csv").read_text().splitlines()[0].split(",")
    # Both players' losses and D's outputs are logged, so a collapsing discriminator is visible.
    for col in ("train/loss_g_step", "train/loss_d_step", "train/d_real_step", "train/d_fake_step", "val_ssim", "lr/g"):
        assert col in csv, col
    from PIL import Image

    grid = Image.open(run_dir / "grids/epoch_001.png")
    assert grid.size == (5 * 32, 3 * 32)


def test_learning_rate_schedule_decays(trained):
    run_dir, _, _ = trained
    rows = list(csv.DictReader(open(run_dir / "metrics.csv")))
    lrs = [float(r["lr/g"]) for r in rows if r.get("lr/g")]
    # 2 epochs, the last decaying linearly (pix2pix): 2e-4, then 2e-4 * (1 - 1/2).
    assert lrs == pytest.approx([2e-4, 1e-4])


def test_load_generator_reproduces_outputs(trained):
    run_dir, system, _ = trained
    loaded = load_generator(run_dir / "last.ckpt", "cpu")
    assert not loaded.training and loaded.generator_name == "tn_cgan"
    # Channels-last, as trained: the faster convolutions on a CPU (oneDNN) and a GPU (cuDNN).
    kernels = [
        m.weight for m in loaded.generator.modules() if isinstance(m, torch.nn.Conv2d) and m.kernel_size != (1, 1)
    ]
    assert kernels and all(w.is_contiguous(memory_format=torch.channels_last) for w in kernels)
    batch = make_pairs(3, 32, seed=5)
    system.eval()
    with torch.no_grad():
        assert torch.allclose(loaded.generate(batch), system.generator.generate(batch), atol=1e-6)
    ckpt = torch.load(run_dir / "last.ckpt", weights_only=True)
    assert ckpt["tnf"]["generator"]["name"] == "tn_cgan"
    assert not any("class_path" in k or "_target_" in k for k in json.dumps(ckpt["hyper_parameters"]))


@pytest.mark.parametrize("order", [(1, 0, 2), (2, 1, 0)])
def test_mirror_averaged_generation_is_exactly_mirror_symmetric(trained, order):
    # Averaged with its own image of the mirrored touch, the generator's image of a mirrored touch is the
    # mirror image of its image of the touch, whatever its weights; on its own it is not.
    _, system, _ = trained
    system.train()
    batch = make_pairs(3, 32, seed=5)
    mirrored = {**batch, **mirror_batch(batch, order)}
    assert torch.equal(mirror_batch(mirrored, order)["tactile"], batch["tactile"])  # the mirror is its own inverse
    expect = mirror_batch({"tactile": system.generate(batch, order)}, order)["tactile"]
    torch.testing.assert_close(system.generate(mirrored, order), expect, atol=1e-5, rtol=0)
    plain = mirror_batch({"tactile": system.generate(batch)}, order)["tactile"]
    assert (system.generate(mirrored) - plain).abs().max() > 1e-3
    assert system.training  # generate() runs in eval mode and leaves the mode as it was


def test_load_errors(trained, tmp_path):
    from tnf.artifacts import CACHE_VERSION

    run_dir, _, _ = trained
    with pytest.raises(TnfError, match="not found"):
        load_generator(tmp_path / "missing.ckpt")
    bad = tmp_path / "bad.ckpt"
    torch.save({"state_dict": {}}, bad)
    with pytest.raises(TnfError, match="not a tnf generator checkpoint"):
        load_generator(bad)
    ckpt = torch.load(run_dir / "last.ckpt", weights_only=True)
    ckpt["tnf"]["format"] = 99
    torch.save(ckpt, bad)
    with pytest.raises(TnfError, match="format 99"):
        load_generator(bad)
    ckpt["tnf"]["format"] = CACHE_VERSION
    ckpt["tnf"]["generator"]["ngf"] = 8  # weights of another architecture
    torch.save(ckpt, bad)
    with pytest.raises(TnfError, match="does not fit"):
        load_generator(bad)
    with pytest.raises(TnfError, match="expected 'lee'"):
        load_generator(run_dir / "last.ckpt", expected="lee")


def test_a_checkpoint_of_an_earlier_cache_version_is_refused_in_one_line(trained, tmp_path):
    from tnf.artifacts import CACHE_VERSION

    run_dir, _, _ = trained
    ckpt = torch.load(run_dir / "last.ckpt", weights_only=True)
    assert ckpt["tnf"]["format"] == CACHE_VERSION
    ckpt["tnf"]["format"] = CACHE_VERSION - 1
    torch.save(ckpt, tmp_path / "older.ckpt")
    with pytest.raises(TnfError, match=f"format {CACHE_VERSION - 1} .*this tnf reads format {CACHE_VERSION}") as e:
        load_generator(tmp_path / "older.ckpt")
    assert "\n" not in str(e.value)


def test_a_checkpoint_of_a_plugin_not_installed_names_the_package(trained, tmp_path):
    run_dir, _, _ = trained
    ckpt = torch.load(run_dir / "last.ckpt", weights_only=True)
    assert ckpt["tnf"]["origin"] == "tnf"  # the distribution that registers the generator
    ckpt["tnf"]["generator"]["name"] = "tiny_p2p"
    ckpt["tnf"]["origin"] = "tnf-tiny"
    torch.save(ckpt, tmp_path / "plugin.ckpt")
    with pytest.raises(TnfError, match=r"generator 'tiny_p2p' of the package 'tnf-tiny', .*pip install tnf-tiny"):
        load_generator(tmp_path / "plugin.ckpt")


def test_resume_continues_from_last(tmp_path):
    run_dir = tmp_path / "run"
    _, s1 = train(run_dir, epochs=1)
    assert s1["epochs"] == 1
    steps = s1["global_step"]
    system = GeneratorSystem(SPEC, epochs=2, decay_epochs=1, grid_rows=3, finite_check_every=1)
    # Same run config -> resume from last.ckpt: only the second epoch runs.
    with pytest.raises(TnfError, match="another config"):
        train(run_dir, epochs=2, system=system)
    _, s2 = train(run_dir, epochs=1, system=GeneratorSystem(SPEC, epochs=2, decay_epochs=1, finite_check_every=1))
    assert s2["epochs"] == 2 and s2["global_step"] == 2 * steps
    # The finished run's metrics.csv holds both parts, each step's rows once.
    rows = list(csv.DictReader(open(run_dir / "metrics.csv")))
    assert [int(r["epoch"]) for r in rows if r["val_l1"]] == [0, 1]
    assert [int(r["step"]) for r in rows if r["train/loss_g_step"]] == list(range(2 * steps // 2))
    assert sorted(p.name for p in run_dir.glob("*.csv")) == ["metrics.csv"]


def test_resuming_keeps_the_rows_of_the_epochs_its_checkpoint_holds(tmp_path):
    """Rows of the epochs after the checkpoint, which the resumed run logs again, are dropped; the columns stay."""
    metrics = tmp_path / "metrics.csv"
    metrics.write_text("epoch,step,train/loss,val_l1\n0,0,5,\n0,1,4,\n0,1,,0.5\n1,2,3,\n1,3,2.5,\n2,4,2,\n")
    keep_epochs(metrics, 2)
    assert metrics.read_text() == "epoch,step,train/loss,val_l1\n0,0,5,\n0,1,4,\n0,1,,0.5\n1,2,3,\n1,3,2.5,\n"
    keep_epochs(metrics, 1)
    assert [r["step"] for r in csv.DictReader(open(metrics))] == ["0", "1", "1"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.csv"]  # no temporary file left behind
    keep_epochs(tmp_path / "missing.csv", 1)
    assert not (tmp_path / "missing.csv").exists()


def test_last_checkpoint_is_in_place_only_once_its_epochs_rows_are_written(tmp_path):
    """Whenever last.ckpt is there, metrics.csv holds every row of the epochs it holds, the epoch's training
    metrics (logged after the checkpoint is saved) included: a run killed at any moment loses no row."""
    from lightning.pytorch.callbacks import Checkpoint

    run_dir = tmp_path / "run"
    seen = []

    class Look(Checkpoint):  # a checkpoint callback: runs after LatestCheckpoint has saved at an epoch's end
        def look(self, *_):
            last = run_dir / "last.ckpt"
            if not last.is_file():
                seen.append(None)
                return
            epoch = torch.load(last, weights_only=True)["epoch"]
            rows = list(csv.DictReader(open(run_dir / "metrics.csv")))
            ended = [int(r["epoch"]) for r in rows if r.get("lr/g")]  # the rows of the epochs' training metrics
            assert ended[: epoch + 1] == list(range(epoch + 1)), (epoch, ended)
            seen.append(epoch)

        on_train_epoch_end = on_train_epoch_start = on_train_batch_end = on_validation_end = look

    train(run_dir, epochs=3, callbacks=[*build_callbacks(), Look()])
    assert seen[-1] == 1 and 0 in seen  # last.ckpt of the final epoch is put in place when training ends
    assert torch.load(run_dir / "last.ckpt", weights_only=True)["epoch"] == 2
    assert not list(run_dir.glob("*.pending"))


def test_last_checkpoint_interval_skips_epochs_but_keeps_the_final_one(tmp_path):
    """With an hour between writes, last.ckpt is written after the first epoch, not after the second, and after
    the last; best.ckpt holds the weights without the optimiser's state."""
    run_dir = tmp_path / "run"
    seen = []

    class Watch(GeneratorSystem):
        def on_train_epoch_start(self):
            last = run_dir / "last.ckpt"
            seen.append(torch.load(last, weights_only=True)["epoch"] if last.is_file() else None)
            super().on_train_epoch_start()

    system = Watch(SPEC, epochs=3, decay_epochs=1, grid_rows=3, finite_check_every=1)
    _, summary = train(run_dir, epochs=3, system=system, checkpoint_every_s=3600)
    assert summary["epochs"] == 3
    assert seen == [None, 0, 0]  # written after epoch 0; epoch 1's write skipped
    last = torch.load(run_dir / "last.ckpt", weights_only=True)
    assert last["epoch"] == 2 and "optimizer_states" in last
    best = torch.load(run_dir / "best.ckpt", weights_only=True)
    assert "optimizer_states" not in best and best["state_dict"].keys() == last["state_dict"].keys()
    assert load_generator(run_dir / "best.ckpt").generator_name == "tn_cgan"


def test_negative_checkpoint_interval_is_refused_before_training(tmp_path):
    with pytest.raises(TnfError, match="checkpoint_every_s"):
        train(tmp_path / "run", epochs=1, checkpoint_every_s=-1)
    assert not (tmp_path / "run").exists()


def test_nan_loss_stops_and_keeps_last_good_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    train(run_dir, epochs=1)
    good = sha(run_dir / "last.ckpt")
    dm = SyntheticPairs(n_train=8, n_val=4, size=32, batch_size=4)
    dm.train["tactile"][5] = float("nan")  # a corrupt pair in the second batch
    system = GeneratorSystem(SPEC, epochs=2, decay_epochs=1, finite_check_every=1)
    with pytest.raises(NonFiniteLoss, match="non-finite training loss .*last good checkpoint"):
        train(run_dir, epochs=1, dm=dm, system=system)
    assert sha(run_dir / "last.ckpt") == good
    assert torch.load(run_dir / "last.ckpt", weights_only=True)["epoch"] == 0


@pytest.mark.parametrize(
    ("change", "says"),
    [
        (lambda out: (out + 1) * 3, r"returned images in \[.*\]"),
        (lambda out: out[:, :1], r"returned images of shape \[4, 1, 32, 32\], expected \[4, 3, 32, 32\]"),
        (lambda out: out * float("nan"), r"returned non-finite images \(12288 NaN or Inf values\)"),
        (lambda out: ((out + 1) * 127.5).to(torch.uint8), "returned torch.uint8 images"),
        (lambda out: (out,), "returned a tuple, not a tensor"),
    ],
)
def test_a_generators_bad_images_are_one_line(tmp_path, change, says):
    """A generator whose ``generate()`` breaks its contract stops validation (and generation) in one line that
    says what it returned and what it must, rather than being scored (or failing deep inside the metrics)."""
    system = GeneratorSystem(SPEC, epochs=1, decay_epochs=0)
    real = system.generator.generate
    system.generator.generate = lambda batch: change(real(batch))
    batch = make_pairs(4)
    system.eval()  # as in validation
    system.on_validation_epoch_start()
    must = r".*must return float images \[B, 3, H, W\] in \[-1, 1\]"
    with pytest.raises(TnfError, match=f"generator 'tn_cgan' {says}{must}"):
        system.validation_step(batch, 0)
    with pytest.raises(TnfError, match=f"generator 'tn_cgan' {says}"):
        system.generate({k: v for k, v in batch.items() if k != "tactile"})
    system.generator.generate = real
    assert system.validation_step(batch, 0)["fake"].shape == (4, 3, 32, 32)


def test_finetune_changes_only_unfrozen_parameters(trained, tmp_path):
    run_dir, _, _ = trained
    src = run_dir / "best.ckpt"
    before = sha(src)
    system = GeneratorSystem.from_checkpoint(src, "cpu", generator_overrides={"lr": 1e-3}, epochs=1, decay_epochs=0)
    start = {k: v.clone() for k, v in system.generator.state_dict().items()}
    src_state = torch.load(src, weights_only=True)["state_dict"]
    assert all(torch.equal(start[k], src_state["generator." + k]) for k in start)  # starts from the checkpoint
    frozen = system.generator.freeze(["net_g.encoders.rgb", "net_g.encoders.depth_and_slope"])
    assert frozen and all(n.startswith("net_g.encoders.") for n in frozen)
    dm = SyntheticPairs(n_train=8, n_val=4, size=32, batch_size=4, seed=7)
    train(tmp_path / "ft", epochs=1, dm=dm, system=system)
    end = system.generator.state_dict()
    for k in start:
        same = torch.equal(start[k], end[k])
        if k.startswith(("net_g.encoders.rgb", "net_g.encoders.depth_and_slope")):
            assert same, f"frozen {k} changed"
        elif (
            k.endswith(".weight")
            and "encoders.background" in k
            or k.startswith("net_g.decoder")
            and k.endswith(".weight")
        ):
            assert not same, f"trainable {k} did not change"
    assert sha(src) == before  # the source checkpoint is untouched
    ft = load_generator(tmp_path / "ft" / "last.ckpt")
    assert ft.hparams["generator"]["lr"] == 1e-3


def test_image_grid_layout():
    b = make_pairs(2, 16)
    b["fake"] = b["tactile"].clone()
    grid = image_grid(b)
    assert grid.shape == (32, 80, 3) and grid.dtype.name == "uint8"
    assert grid[:, 64:].max() == 0  # identical images: the difference column is black
    assert (grid[:, 32:48] == grid[:, 48:64]).all()  # generated == target


def test_loggers(tmp_path):
    from tnf.generators.training import make_loggers

    assert [type(x).__name__ for x in make_loggers({"name": "csv"}, tmp_path)] == ["RunCSVLogger"]
    with pytest.raises(TnfError, match="unknown logger 'mlflow'"):
        make_loggers({"name": "mlflow"}, tmp_path)
    wandb = make_loggers({"name": "wandb", "project": "tnf", "mode": "offline"}, tmp_path)
    assert [type(x).__name__ for x in wandb] == ["RunCSVLogger", "WandbLogger"]


def _epoch_rows(run_dir):
    return [r for r in csv.DictReader(open(run_dir / "metrics.csv")) if r.get("train/d_saturated")]


def test_discriminator_saturation_is_logged_each_epoch(trained):
    """train/d_saturated follows the epoch's mean D outputs, which are logged beside it."""
    run_dir, _, _ = trained
    rows = _epoch_rows(run_dir)
    assert len(rows) == 2
    t = DiscriminatorWatch.Config().threshold
    for r in rows:
        expected = discriminator_saturated(float(r["train/d_real_epoch"]), float(r["train/d_fake_epoch"]), t)
        assert float(r["train/d_saturated"]) == float(expected)
    assert t == 0.95  # conf/callbacks/default.yaml
    assert discriminator_saturated(0.99, 0.01, t) and not discriminator_saturated(0.99, 0.2, t)
    assert not discriminator_saturated(0.6, 0.4, t)


def test_training_without_the_adversarial_term(tmp_path, recwarn):
    """lambda_gan = 0 through Lightning: only the generator's optimiser and schedule, no discriminator columns,
    no warnings about schedules stepping an optimiser that never stepped."""
    spec = {**SPEC, "lambda_gan": 0.0}
    system = GeneratorSystem(spec, epochs=2, decay_epochs=1, grid_rows=3, finite_check_every=1)
    train(tmp_path / "run", epochs=2, system=system)
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    lr = [float(r["lr/g"]) for r in rows if r["lr/g"]]
    assert len(lr) == 2 and lr[0] > lr[1]  # the schedule ran
    assert len([r for r in rows if r["val_l1"]]) == 2
    header = list(rows[0])
    assert not [c for c in header if c.startswith(("lr/d", "train/loss_d", "train/d_"))], header
    assert not [w for w in recwarn if "lr_scheduler.step()" in str(w.message)]


def test_a_discriminator_that_wins_is_reported(tmp_path, caplog):
    """A generator that cannot learn (learning rate 0) against a fast discriminator: D soon tells the pairs apart
    every time, and the epoch it starts is logged as a warning and as train/d_saturated = 1."""

    class FrozenGenerator(GeneratorSystem):
        def configure_optimizers(self):
            opts, scheds = super().configure_optimizers()
            for o, s, name in zip(opts, scheds, self.generator.optimizer_names):
                lr = 0.0 if name == "g" else 2e-3
                s.base_lrs = [lr] * len(o.param_groups)  # the schedule scales these each epoch
                for g in o.param_groups:
                    g["lr"] = lr
            return opts, scheds

    system = FrozenGenerator(SPEC, epochs=5, decay_epochs=0, grid_rows=3, finite_check_every=1)
    dm = SyntheticPairs(n_train=32, n_val=4, size=32, batch_size=4)
    with caplog.at_level("WARNING", logger="tnf.generators.callbacks"):
        train(tmp_path / "run", epochs=5, system=system, dm=dm)
    rows = _epoch_rows(tmp_path / "run")
    flags = [float(r["train/d_saturated"]) for r in rows]
    assert len(flags) == 5 and flags[0] == 0.0 and flags[-1] == 1.0, flags
    first = flags.index(1.0)
    msgs = [m for m in caplog.messages if "discriminator tells real from generated" in m]
    assert len(msgs) == 1 and msgs[0].startswith(f"epoch {first}:")
    assert "try generator.gan_mode=lsgan or generator.lambda_gan=0 or another seed" in msgs[0]


# -- the weights' exponential moving average (ema_decay) ------------------------------------------------------------
def test_weight_average_follows_its_decay_and_warm_up():
    torch.manual_seed(0)
    system = GeneratorSystem(SPEC, ema_decay=0.5)
    average = WeightAverage()
    start = [p.clone() for p in system.generator.parameters()]
    assert all(torch.equal(a, p) for a, p in zip(system.generator_ema.parameters(), start, strict=True))
    assert not any(p.requires_grad for p in system.generator_ema.parameters())
    expect = [p.clone() for p in start]
    for n, shift in enumerate([1.0, -2.0, 0.5]):
        with torch.no_grad():
            for p in system.generator.parameters():
                p.add_(shift)
        average.update(system)
        decay = min(0.5, (1 + n) / (10 + n))  # 0.1, 2/11, 0.25: the first updates follow the weights closely
        expect = [decay * e + (1 - decay) * p for e, p in zip(expect, system.generator.parameters(), strict=True)]
        for a, e in zip(system.generator_ema.parameters(), expect, strict=True):
            torch.testing.assert_close(a, e, atol=1e-6, rtol=0)
    assert int(system.ema_updates) == 3
    for bad in (1.0, 0, "fast", True):
        with pytest.raises(TnfError, match="ema_decay must be in"):
            GeneratorSystem(SPEC, ema_decay=bad)


@pytest.fixture(scope="module")
def averaged_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("models") / "ema"
    torch.manual_seed(0)
    # A high learning rate, so that the average and the weights it follows generate visibly different images.
    spec = {**SPEC, "lr": 5e-3}
    system = GeneratorSystem(spec, epochs=2, decay_epochs=1, grid_rows=0, finite_check_every=1, ema_decay=0.9)
    train(run_dir, epochs=2, system=system)
    return run_dir, system


def test_weight_average_validates_generates_and_is_checkpointed(averaged_run):
    run_dir, system = averaged_run
    state = torch.load(run_dir / "best.ckpt", weights_only=True)["state_dict"]
    assert int(state["ema_updates"]) == system.global_step // 2 == 4  # one update per batch (two optimisers step)
    averaged, trained = load_generator(run_dir / "best.ckpt"), load_generator(run_dir / "best.ckpt", averaged=False)
    assert averaged.generator_ema is None  # a loaded generator carries one set of weights
    for k, v in averaged.generator.state_dict().items():
        torch.testing.assert_close(v, state["generator_ema." + k])
        torch.testing.assert_close(trained.generator.state_dict()[k], state["generator." + k])
    keys = averaged.generator.state_dict()
    assert any(not torch.equal(state["generator." + k], state["generator_ema." + k]) for k in keys)
    # The logged validation L1 is the average's, and best.ckpt's L1 the best one logged.
    val = make_pairs(4, 32, seed=1)  # SyntheticPairs' validation pairs
    manifest = json.loads((run_dir / "manifest.json").read_text())

    def l1(g):
        return float((g.generate(val) - val["tactile"]).abs().mean())

    assert l1(averaged) == pytest.approx(manifest["best_val_l1"], abs=1e-6)
    assert abs(l1(trained) - manifest["best_val_l1"]) > 1e-4  # 100 times the tolerance above


def test_weight_average_resumes_with_its_update_count(tmp_path):
    run_dir = tmp_path / "run"
    first = GeneratorSystem(SPEC, epochs=1, decay_epochs=1, finite_check_every=1, ema_decay=0.9)
    train(run_dir, epochs=1, system=first)  # a run of one epoch, then resumed for a second
    saved = torch.load(run_dir / "last.ckpt", weights_only=True)["state_dict"]
    assert int(saved["ema_updates"]) == 2
    resumed = GeneratorSystem(SPEC, epochs=2, decay_epochs=1, finite_check_every=1, ema_decay=0.9)
    names = [n for n, _ in resumed.generator.named_parameters()]
    weights = []  # the weights each update of the resumed run moves the average towards

    class Recording(WeightAverage):
        def update(self, system):
            weights.append([p.detach().clone() for p in system.generator.parameters()])
            super().update(system)

    train(run_dir, epochs=1, system=resumed, callbacks=[Recording(), *build_callbacks()[1:]])
    assert int(resumed.ema_updates) == 4 and len(weights) == 2
    # The saved average went on with updates 3 and 4 (warm-up decays 3/12 and 4/13), rather than starting again.
    expect = [saved["generator_ema." + n] for n in names]
    for n, w in zip((2, 3), weights, strict=True):
        d = min(0.9, (1 + n) / (10 + n))
        expect = [d * e + (1 - d) * p for e, p in zip(expect, w, strict=True)]
    for a, e in zip(resumed.generator_ema.parameters(), expect, strict=True):
        torch.testing.assert_close(a, e, atol=1e-6, rtol=0)


def test_finetuning_starts_from_the_average(averaged_run):
    run_dir, _ = averaged_run
    state = torch.load(run_dir / "best.ckpt", weights_only=True)["state_dict"]
    plain = GeneratorSystem.from_checkpoint(run_dir / "best.ckpt", "cpu", epochs=1, decay_epochs=0, ema_decay=None)
    assert plain.generator_ema is None
    again = GeneratorSystem.from_checkpoint(run_dir / "best.ckpt", "cpu", epochs=1, decay_epochs=0, ema_decay=0.99)
    for k, v in plain.generator.state_dict().items():
        torch.testing.assert_close(v, state["generator_ema." + k])
        torch.testing.assert_close(again.generator_ema.state_dict()[k], v)  # a fresh average of the start
    assert int(again.ema_updates) == 0


def test_system_builds_from_a_checked_config_as_it_is():
    name, config = generator_config(SPEC)
    system = GeneratorSystem((name, config), epochs=2, decay_epochs=1)
    assert system.generator.cfg is config
    assert system.hparams["generator"] == generator_spec(SPEC) == GeneratorSystem(SPEC).hparams["generator"]


# -- the callbacks config group -------------------------------------------------------------------------------------
def test_callbacks_group_builds_each_callback_with_its_settings():
    from tnf.testing import compose

    cfg = compose("train", ["callbacks.image_grids.folder=pictures", "callbacks.discriminator_watch=null"])
    built = build_callbacks(cfg.callbacks)
    assert [type(c).__name__ for c in built] == ["WeightAverage", "FiniteCheck", "ImageGrids", "EpochTimes"]
    assert isinstance(built[2], ImageGrids) and built[2].config.folder == "pictures"
    assert [type(c).__name__ for c in build_callbacks()] == [
        "WeightAverage",
        "FiniteCheck",
        "DiscriminatorWatch",
        "ImageGrids",
        "EpochTimes",
    ]
    with pytest.raises(TnfError, match="unknown callback 'early_stop'.*available: weight_average"):
        build_callbacks({"early_stop": {}})
    with pytest.raises(TnfError, match="callbacks.image_grids: unknown key 'rows'"):
        build_callbacks({"image_grids": {"rows": 3}})
    with pytest.raises(TnfError, match="callbacks.discriminator_watch: threshold must be in"):
        build_callbacks({"discriminator_watch": {"threshold": 0.2}})


def test_callbacks_left_out_leave_their_outputs_out(tmp_path):
    """Without the grids and the watcher: no grids folder and no train/d_saturated column; the grids' folder is
    a setting."""
    run_dir = tmp_path / "run"
    train(run_dir, epochs=1, callbacks=build_callbacks({"weight_average": {}, "finite_check": {}}))
    assert not (run_dir / "grids").exists()
    header = (run_dir / "metrics.csv").read_text().splitlines()[0].split(",")
    assert "train/d_real_epoch" in header and "train/d_saturated" not in header
    train(tmp_path / "other", epochs=1, callbacks=build_callbacks({"image_grids": {"folder": "pictures"}}))
    assert sorted(p.name for p in (tmp_path / "other" / "pictures").iterdir()) == ["epoch_000.png"]


def test_epoch_times_split_each_epoch_into_training_validation_and_the_rest(tmp_path):
    """Every epoch's row holds the three times; validation runs inside the epoch (before its end), so its time
    is measured; the first epoch has nothing before it, the second the first one's checkpoint writing."""
    run_dir = tmp_path / "run"
    train(run_dir, epochs=2, callbacks=build_callbacks({"finite_check": {}, "epoch_times": {}}))
    rows = [r for r in csv.DictReader(open(run_dir / "metrics.csv")) if r.get("time/train_s")]
    assert len(rows) == 2
    for r in rows:
        assert float(r["time/train_s"]) > 0 and float(r["time/val_s"]) > 0
    assert float(rows[0]["time/other_s"]) == 0.0 and float(rows[1]["time/other_s"]) > 0


def test_a_weight_average_without_its_callback_is_refused(tmp_path):
    system = GeneratorSystem(SPEC, epochs=1, decay_epochs=0, ema_decay=0.9)
    with pytest.raises(TnfError, match="weight_average callback"):
        train(tmp_path / "run", epochs=1, system=system, callbacks=build_callbacks({"finite_check": {}}))
    assert not (tmp_path / "run").exists()
