"""Surface points (``pair.points``) and a generator with a surface field (``generator=tn_cgan_surface``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tnf.cli import main
from tnf.data import PairDataset, open_pairs, training_order
from tnf.data.dataset import MixedPairDataset, mirror_batch
from tnf.data.render import Framing, render_rgbd_crops
from tnf.errors import TnfError
from tnf.registry import SENSORS

MESH = ["debug=tiny", "progress=false", "device=cpu", "sensor.noise_std=0", "pair.scene_source=mesh"]


@pytest.fixture(scope="module")
def point_pairs(tmp_path_factory):
    root = tmp_path_factory.mktemp("surface") / "tnf-data"
    for stage in ("capture", "touch", "pair"):
        assert main([stage, f"data_root={root}", *MESH, "pair.points=true"]) == 0
    return root / "pairs" / "digit-mesh"


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal, NaN included (no surface under a pixel)."""
    return torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(), b.nan_to_num())


def _look_at(eye: np.ndarray) -> torch.Tensor:
    """A camera at ``eye`` looking at the origin (OpenGL: along -z)."""
    z = eye / np.linalg.norm(eye)
    x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    c2w[:3, 3] = eye
    return torch.tensor(c2w, dtype=torch.float32)


def test_each_pixels_point_lies_on_the_surface_it_sees():
    from tests.data.pair_inputs import SphereScene

    scene = SphereScene(SphereScene.Config(radius=0.04))
    sensor = SENSORS.build({"name": "digit", "width": 60, "height": 80})
    c2w = torch.stack([_look_at(np.array([0.0, 0.0, 0.1])), _look_at(np.array([0.06, -0.03, 0.05]))])
    for extent in ("sensor", "footprint"):
        framing = Framing(crop_extent=extent).with_sensor(sensor)
        crops = render_rgbd_crops(scene, c2w, (60.0, 60.0), (0.019, 0.025), framing, with_points=True)
        pts = crops.points
        assert pts is not None and pts.shape == (2, 128, 128, 3) and pts.dtype == np.float32
        hit = np.isfinite(pts).all(-1)
        assert hit.mean() > 0.5
        radius = np.linalg.norm(pts[hit], axis=-1)
        assert np.abs(radius - 0.04).max() < 2e-5  # on the sphere, to the renderer's precision
        # Every pixel with a depth in the crop's window has a point (farther surfaces too, beyond the window).
        assert ((crops.depth < 1) <= hit).all()
        # The centre ray meets the sphere where the camera looks: the point nearest the camera.
        centre = pts[:, 63:65, 63:65].mean((1, 2))
        eye = c2w[:, :3, 3].numpy()
        assert np.allclose(centre, 0.04 * eye / np.linalg.norm(eye, axis=1, keepdims=True), atol=3e-4)
    # Without asking, no points are made.
    assert render_rgbd_crops(scene, c2w, (60.0, 60.0), (0.019, 0.025), framing).points is None


def test_the_dataset_stores_and_serves_the_points(point_pairs):
    a = open_pairs(point_pairs)
    assert a.manifest["points"] == {"frame": "object", "unit": "m"}
    assert a.points is not None and a.points.shape == (len(a), 128, 128, 3) and a.points.dtype == np.float32
    hit = np.isfinite(a.points).all(-1)
    assert hit.mean() > 0.2
    # Built-in objects fit in a 30 cm box around their origin.
    assert np.abs(a.points[hit]).max() < 0.3
    ds = PairDataset(point_pairs, splits=("train", "val"))
    b = ds.__getitems__([0, 1, 2])
    want = torch.from_numpy(np.array(a.points[ds.index[:3]])).permute(0, 3, 1, 2)
    assert b["points"].shape == (3, 3, 128, 128) and _same(b["points"], want)
    # Compact batches (converted on the training device) serve them the same way: they are float32 as stored.
    compact = PairDataset(point_pairs, splits=("train", "val"), compact=True).__getitems__([0, 1, 2])
    from tnf.data.dataset import to_float_batch

    assert _same(compact["points"], want) and _same(to_float_batch(compact)["points"], want)
    # The mirror flips the points with the image and keeps their values (no channel reordering).
    m = mirror_batch(b, SENSORS.build({"name": "digit"}).mirror_channels())
    assert _same(m["points"], b["points"].flip(-1))
    # Mixed with a dataset without points, the batches carry none.
    plain = point_pairs.parent / "plain"
    plain.mkdir()
    for f in point_pairs.iterdir():
        if f.suffix == ".npy" and f.name != "points.npy":
            (plain / f.name).symlink_to(f)
    from tnf.artifacts import MANIFEST, read_json, write_json

    write_json(plain / MANIFEST, {**read_json(point_pairs / MANIFEST, "manifest"), "points": None})
    n = len(PairDataset(point_pairs))
    assert "points" not in MixedPairDataset([PairDataset(point_pairs), PairDataset(plain)]).__getitems__([0, n])


def test_a_surface_generator_trains_generates_and_names_what_it_needs(point_pairs):
    from tests.data.pair_inputs import SphereScene
    from tnf.generators import load_generator
    from tnf.registry import GENERATORS
    from tnf.scenes import save_scene
    from tnf.stages import evaluate, generate, train
    from tnf.testing import compose

    gen = GENERATORS.build({"name": "tn_cgan", "ngf": 8, "ndf": 8, "inputs": ["rgb", "background", "surface"],
                            "skips": ["background"]})  # fmt: skip
    batch = {k: v for k, v in PairDataset(point_pairs).__getitems__([0, 1]).items() if k != "points"}
    with pytest.raises(TnfError, match="pair.points=true"):
        gen.generate(batch)

    root = point_pairs.parents[1]
    base = [f"data_root={root}", "debug=tiny", "progress=false", "device=cpu", "data.batch_size=4"]
    model = ["generator=tn_cgan_surface", "generator.surface_log2_table=12", "data.datasets=[digit-mesh]"]
    train.run(compose("train", [*base, *model, "train.run_name=surface", "train.epochs=1", "train.decay_epochs=0"]))
    system = load_generator(root / "models" / "surface" / "best.ckpt", "cpu")
    field = system.generator.field
    names = open_pairs(point_pairs).objects
    novel = open_pairs(point_pairs).manifest["novel_objects"]
    # The field knows the objects it was trained on, and only those.
    assert [bool(field.seen[i]) for i in range(len(names))] == [n not in novel for n in names]
    assert field.table.abs().max() > 1e-3  # training wrote into it (it starts within 1e-4 of zero)
    # Generating novel touches of a trained object: each pixel's point is looked up in the field.
    trained = next(n for n in names if n not in novel)
    save_scene(SphereScene(SphereScene.Config(radius=0.04)), root / "scenes" / "hashgrid" / "builtin" / trained)
    args = [*base, f"object={trained}", "generate.model=surface", "generate.n_poses=3", "generate.radius=0.1"]
    assert generate.run(compose("generate", args))["written"] == {trained: 3}
    # Fine-tuning keeps the field's object ids: on data of the same objects it runs and records them; on data
    # that orders them otherwise it stops before training, rather than teach the field the wrong objects.
    from tnf.artifacts import read_json
    from tnf.stages import finetune

    ft = [*base, "data.datasets=[digit-mesh]", "finetune.checkpoint=surface", "finetune.epochs=1"]
    finetune.run(compose("finetune", [*ft, "finetune.decay_epochs=0", "finetune.run_name=surface_ft"]))
    assert read_json(root / "models" / "surface_ft" / "manifest.json", "manifest")["object_names"] == names
    swapped = ["pair.name=swapped", f"object_names=[{','.join(reversed(names))}]"]
    assert main(["pair", f"data_root={root}", *MESH, "pair.points=true", *swapped]) == 0
    with pytest.raises(TnfError, match="same objects in the same order"):
        finetune.run(compose("finetune", [*ft, "data.datasets=[swapped]", "finetune.run_name=surface_swapped"]))
    assert not (root / "models" / "surface_swapped").exists()
    # The test splits are scored with the ids the field was trained with.
    ev = [*base, "evaluate.model=surface", "evaluate.dataset=digit-mesh", "evaluate.classify.enabled=false"]
    results = evaluate.run(compose("evaluate", ev))["results"]
    for split, objects in (("novel_view", {trained}), ("novel_object", set(novel))):
        row = results["image"][split]["T-N"]
        assert set(row["per_object"]) == objects and row["n"] == 4 and 0 < row["ssim"] <= 1


def test_object_ids_follow_the_models_training_order():
    # A model trained on [mug, ball] scores a dataset of [ball, cup, mug]: its objects keep their training ids,
    # the new one comes after; a model that records no order leaves the dataset's own.
    assert training_order(["mug", "ball"], ["ball", "cup", "mug"]) == ["mug", "ball", "cup"]
    assert training_order(None, ["ball", "cup"]) is None and training_order([], ["ball"]) is None
