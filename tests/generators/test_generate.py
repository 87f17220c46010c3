"""`tnf generate`: novel poses -> rendered RGB-D -> generator -> a dataset in the format of `tnf touch`."""

import json

import numpy as np
import pytest
from PIL import Image

from tests.data.pair_inputs import SphereScene
from tests.generators.test_stages import TINY, write_pairs
from tnf.artifacts import write_json
from tnf.data.render import TouchItem
from tnf.errors import TnfError
from tnf.scenes import save_scene
from tnf.testing import compose

SHORT = ["train.epochs=1", "train.decay_epochs=0"]


@pytest.fixture
def trained_model(data_root):
    from tnf.stages import train

    write_pairs(data_root / "pairs" / "digit-hashgrid", n=6)
    out = train.run(compose("train", [*TINY, *SHORT]))
    # The object's fitted scene and the capture camera the crop is measured in.
    save_scene(SphereScene(SphereScene.Config(radius=0.04)), data_root / "scenes" / "hashgrid" / "builtin" / "ball")
    write_json(
        data_root / "capture" / "builtin" / "ball" / "transforms.json",
        {"fl_x": 200.0, "fl_y": 200.0, "w": 128, "h": 128},
    )
    return out["run_name"]


GEN = [*TINY, "object=ball", "device=cpu", "generate.crop_px=48", "generate.radius=0.1"]


def test_generate_writes_a_touch_dataset(data_root, trained_model):
    from tnf.stages import generate

    out = generate.run(
        compose("generate", [*GEN, f"generate.model={trained_model}", "generate.n_poses=5", "generate.batch_size=2"])
    )
    folder = data_root / "generated" / trained_model / "builtin" / "ball"
    assert out["written"] == {"ball": 5}
    item = TouchItem.load(folder)  # what `tnf pair` and the evaluation read
    assert len(item.touches) == 5
    assert {t.split for t in item.touches} == {"train"}
    poses = item.start_poses()
    assert np.allclose(np.linalg.norm(poses[:, :3, 3], axis=1), 0.1)
    # Each camera looks at the object centre, so its centre ray hits the sphere at 0.04 m from the centre.
    pts = np.array([t.contact_point for t in item.touches])
    assert np.allclose(np.linalg.norm(pts, axis=1), 0.04, atol=2e-3)
    img = np.asarray(Image.open(folder / item.touches[0].image))
    assert img.shape == (128, 128, 3) and img.dtype == np.uint8 and img.std() > 0
    assert (folder / "background.png").is_file()
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["sensor"]["name"] == "digit" and manifest["generator"]["name"] == "tn_cgan"
    # Same settings again, the model left to its default (the one `tnf train` trains with this config): nothing to do.
    assert generate.run(compose("generate", [*GEN, *SHORT, "generate.n_poses=5"]))["written"] == {}


def test_generate_from_a_poses_file(data_root, trained_model, tmp_path):
    from tnf.cameras import look_at
    from tnf.stages import generate

    poses = np.stack(
        [
            look_at(np.array(e, float), np.zeros(3), fallback="parallel")
            for e in ([0.1, 0, 0], [0, 0.12, 0.0], [0, 0, -0.1])
        ]
    )
    np.save(tmp_path / "poses.npy", poses)
    out = generate.run(
        compose(
            "generate",
            [
                *GEN,
                f"generate.model={trained_model}",
                f"generate.poses_file={tmp_path / 'poses.npy'}",
                "generate.run_name=fromfile",
            ],
        )
    )
    assert out["written"] == {"ball": 3}
    item = TouchItem.load(data_root / "generated" / "fromfile" / "builtin" / "ball")
    assert np.allclose(item.start_poses(), poses)


def test_generate_in_the_held_out_cone(data_root, trained_model):
    """directions=novel_view: every pose looks from inside the touch stage's held-out cone (the views the
    ground-truth touches lack); with directions=sphere the same seed spreads them over every direction."""
    from tnf.stages import generate

    cone = ["touch.novel_view_axis=[0.0,1.0,0.0]", "touch.novel_view_cone=20.0", "generate.n_poses=6"]
    runs = {"cone": ["generate.directions=novel_view"], "sphere": []}
    for name, extra in runs.items():
        over = [*GEN, f"generate.model={trained_model}", *cone, *extra, f"generate.run_name={name}"]
        assert generate.run(compose("generate", over))["written"] == {"ball": 6}
    cos = {}
    for name in runs:
        poses = TouchItem.load(data_root / "generated" / name / "builtin" / "ball").start_poses()
        cos[name] = poses[:, 1, 3] / np.linalg.norm(poses[:, :3, 3], axis=1)  # direction of each pose about +y
    assert (cos["cone"] >= np.cos(np.radians(20.0)) - 1e-9).all()
    assert (cos["sphere"] < np.cos(np.radians(20.0))).any()
    # each manifest says where its poses came from (the evaluation's report reads it)
    sources = {
        n: json.loads((data_root / "generated" / n / "builtin/ball/manifest.json").read_text())["poses"] for n in runs
    }
    assert sources == {
        "cone": {"directions": "novel_view", "cone_axis": [0.0, 1.0, 0.0], "cone_deg": 20.0},
        "sphere": {"directions": "sphere"},
    }


def test_generate_directions_errors(data_root, trained_model):
    from tnf.stages import generate

    base = [*GEN, f"generate.model={trained_model}", "generate.n_poses=2"]
    with pytest.raises(TnfError, match="generate.directions: expected one of 'sphere', 'novel_view', got 'cone'"):
        generate.run(compose("generate", [*base, "generate.directions=cone"]))
    with pytest.raises(TnfError, match="needs a held-out cone"):
        generate.run(compose("generate", [*base, "generate.directions=novel_view", "touch.novel_view_cone=0.0"]))
    with pytest.raises(TnfError, match="must be a non-zero 3-vector"):
        generate.run(compose("generate", [*base, "generate.directions=novel_view", "generate.cone_axis=[0,0,0]"]))
    with pytest.raises(TnfError, match=r"must be in \[0, 180\) degrees"):
        generate.run(compose("generate", [*base, "generate.directions=novel_view", "generate.cone_deg=200"]))
    assert not (data_root / "generated" / trained_model).exists()  # refused before anything was written


def test_generate_errors(data_root, trained_model):
    from tnf.stages import generate

    # Without generate.model: the model `tnf train` trains with the same config, here not trained.
    with pytest.raises(TnfError, match=r"checkpoint not found: .*/models/tn_cgan-digit-hashgrid-seed0-\w+/best.ckpt"):
        generate.run(compose("generate", GEN))
    with pytest.raises(TnfError, match="checkpoint not found"):
        generate.run(compose("generate", [*GEN, "generate.model=nope"]))
    with pytest.raises(TnfError, match="no fitted hashgrid scene"):
        generate.run(
            compose("generate", [*TINY, "object=box", f"generate.model={trained_model}", "generate.crop_px=48"])
        )


def test_generate_frames_novel_poses_as_its_training_dataset(data_root, trained_model):
    # A dataset made with pair.crop_extent=sensor stores the tactile image's gel patch; generation reads the
    # framing from there (the model's first dataset), not from the pair section's defaults.
    from tnf.artifacts import MANIFEST, read_json
    from tnf.stages import generate

    manifest = data_root / "pairs" / "digit-hashgrid" / MANIFEST
    m = read_json(manifest, "dataset manifest")
    m["preprocess"] = {
        "crop_distance": "contact",
        "crop_extent": "sensor",
        "view_size": [0.019, 0.025],
        "footprint_distance": 0.06,
        "crop_margin": 1.5,
        "crop_px": {},
        "depth_norm": "contact",
        "depth_window": 0.04,
    }
    write_json(manifest, m)
    gen = [*TINY, "object=ball", "device=cpu", "generate.radius=0.1", f"generate.model={trained_model}"]
    assert generate.run(compose("generate", [*gen, "generate.n_poses=3"]))["written"] == {"ball": 3}
    config = read_json(data_root / "generated" / trained_model / "builtin" / "ball" / MANIFEST, "manifest")["config"]
    assert config["framing"]["crop_extent"] == "sensor" and config["framing"]["view_size"] == [0.019, 0.025]
    # A fixed crop cannot frame what the model was trained on this way: refused before anything is rendered.
    with pytest.raises(TnfError, match="crop_distance=contact"):
        generate.run(compose("generate", [*gen, "generate.crop_px=48", "generate.run_name=fixed"]))
    # A dataset of another format version (its framing may lack settings) is refused, not read.
    write_json(manifest, {**m, "format_version": 1})
    with pytest.raises(
        TnfError,
        match=r"has format version 1, this tnf reads \d+; rebuild it: `tnf clean pair digit-\w+`, then `tnf pair`",
    ):
        generate.run(compose("generate", [*gen, "generate.n_poses=3", "generate.run_name=old"]))


def test_mirror_averaged_generation(data_root, trained_model, capsys):
    import torch

    from tnf.data import PairDataset, mirror_batch
    from tnf.generators import load_generator
    from tnf.metrics import ssim
    from tnf.stages import evaluate, generate

    def images(run_name, *extra):
        args = [*GEN, f"generate.model={trained_model}", "generate.n_poses=3", f"generate.run_name={run_name}"]
        out = generate.run(compose("generate", [*args, *extra]))
        folder = data_root / "generated" / run_name / "builtin" / "ball"
        return out, [np.asarray(Image.open(folder / t.image)) for t in TouchItem.load(folder).touches]

    _, plain = images("plain")
    out, averaged = images("averaged", "generate.mirror_average=true")
    assert out["written"] == {"ball": 3}
    assert any(not np.array_equal(a, b) for a, b in zip(plain, averaged, strict=True))
    assert images("averaged")[0]["written"] == {"ball": 3}  # switched off again: made again, not "up to date"

    # `tnf evaluate` scores the test images as generate makes them, with the mirror of the dataset's sensor
    # (the Digit's: red and green swap).
    def val_ssim(*extra):
        args = [*TINY, f"evaluate.model={trained_model}", "evaluate.dataset=digit-hashgrid", "evaluate.splits=[val]"]
        args.append("evaluate.classify.enabled=false")
        return evaluate.run(compose("evaluate", [*args, *extra]))["results"]["image"]["val"]["T-N"]["ssim"]

    system = load_generator(data_root / "models" / trained_model / "best.ckpt", "cpu")
    batch = PairDataset(data_root / "pairs" / "digit-hashgrid", ["val"]).__getitems__([0, 1])
    expect = ssim(system.generate(batch, (1, 0, 2)), batch["tactile"]).mean().item()
    assert val_ssim("generate.mirror_average=true", "evaluate.name=averaged") == pytest.approx(expect, abs=1e-5)
    flipped = {**batch, **mirror_batch(batch, (1, 0, 2))}
    assert not torch.allclose(system.generate(flipped, (1, 0, 2)), system.generate(flipped), atol=1e-4)
    assert val_ssim("evaluate.name=plain") != pytest.approx(expect, abs=1e-5)

    # A dataset of a sensor without the symmetry is scored without averaging, and evaluate says so.
    from tnf.artifacts import MANIFEST, read_json

    manifest = data_root / "pairs" / "digit-hashgrid" / MANIFEST
    saved = manifest.read_text()
    m = read_json(manifest, "dataset manifest")
    m["sensor"] = {"name": "omnitact", "config": {}}
    write_json(manifest, m)
    capsys.readouterr()
    try:
        unmirrored = val_ssim("generate.mirror_average=true", "evaluate.name=no_symmetry")
    finally:
        manifest.write_text(saved)
    assert unmirrored == pytest.approx(val_ssim("evaluate.name=plain"), abs=1e-6)
    said = " ".join(capsys.readouterr().out.split())  # the console wraps long lines
    assert "dataset digit-hashgrid has no mirror symmetry; test images are not mirror-averaged" in said


def test_a_model_whose_training_was_cut_short_is_refused_unless_its_dataset_is_named(data_root, trained_model):
    # An interrupted run has checkpoints but no manifest: its framing would silently come from the pair section.
    from tnf.artifacts import MANIFEST
    from tnf.stages import generate

    (data_root / "models" / trained_model / MANIFEST).unlink()
    gen = [*TINY, "object=ball", "device=cpu", "generate.radius=0.1", f"generate.model={trained_model}"]
    with pytest.raises(TnfError, match=rf"model {trained_model} has not finished training .*generate.dataset"):
        generate.run(compose("generate", [*gen, "generate.crop_px=48", "generate.n_poses=2"]))
    assert not (data_root / "generated" / trained_model).exists()
    # Naming the dataset it trains on generates from its checkpoint as it is.
    out = generate.run(
        compose("generate", [*gen, "generate.crop_px=48", "generate.n_poses=2", "generate.dataset=digit-hashgrid"])
    )
    assert out["written"] == {"ball": 2}
