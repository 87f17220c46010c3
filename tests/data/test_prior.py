"""The prior (``pair.prior``): the simulator's image of each depth crop, stored with the pairs and served in batches."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from tnf import metrics
from tnf.cli import main
from tnf.data import PairDataset, open_pairs, resize_uint8
from tnf.data.dataset import mirror_batch
from tnf.data.prior import DepthPrior
from tnf.data.render import Framing
from tnf.errors import TnfError
from tnf.registry import SENSORS

# Built-in meshes, the warp simulator's touches without pixel noise, crops rendered from the same meshes.
MESH = ["debug=tiny", "progress=false", "device=cpu", "sensor.noise_std=0", "pair.scene_source=mesh"]
PRIOR = ["pair.crop_extent=sensor", "pair.prior=true"]


def _sensor_framing(**framing):
    sensor = SENSORS.build({"name": "digit", "width": 60, "height": 80})
    return sensor, Framing(**{"crop_extent": "sensor", **framing}).with_sensor(sensor)


def _images(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.array(x)).permute(0, 3, 1, 2).contiguous()


@pytest.fixture(scope="module")
def mesh_pairs(tmp_path_factory):
    root = tmp_path_factory.mktemp("prior") / "tnf-data"
    for stage in ("capture", "touch", "pair"):
        assert main([stage, f"data_root={root}", *MESH, *PRIOR]) == 0
    return root / "pairs" / "digit-mesh"


def test_prior_of_the_mesh_depth_is_the_simulated_touch(mesh_pairs):
    a = open_pairs(mesh_pairs)
    assert a.manifest["prior"]["simulator"]["name"] == "warp_gel"
    assert a.prior is not None and a.prior.shape == a.tactile.shape and a.prior.dtype == np.uint8
    # The previews show it after the tactile image: RGB | depth | background | tactile | prior.
    preview = sorted((mesh_pairs / "previews").glob("pair_*.png"))[0]
    row = int(preview.name.split("_")[1])
    strip = np.asarray(Image.open(preview))
    assert strip.shape == (128, 5 * 128, 3) and np.array_equal(strip[:, 4 * 128 :], a.prior[row])
    tactile, prior = _images(a.tactile), _images(a.prior)
    background = _images(a.backgrounds[a.background_index])
    pressed = metrics.mse(background, tactile) > 20  # touches whose image shows a press
    assert pressed.sum() >= 10
    # From the exact depth, the prior is close to the touch the simulator made from the mesh itself: far closer
    # than the background is (the crop's perspective and 128 px resampling are what separate them).
    ssim_prior = metrics.ssim(prior[pressed], tactile[pressed]).mean()
    ssim_bg = metrics.ssim(background[pressed], tactile[pressed]).mean()
    mse_prior = metrics.mse(prior[pressed], tactile[pressed]).mean()
    mse_bg = metrics.mse(background[pressed], tactile[pressed]).mean()
    assert ssim_prior > 0.95 and ssim_prior > ssim_bg + 0.03
    assert mse_prior < 0.3 * mse_bg


def test_batches_carry_the_prior_and_the_mirror_treats_it_as_a_sensor_image(mesh_pairs):
    ds = PairDataset(mesh_pairs, splits=("train", "val"))
    b = ds.__getitems__([0, 1, 2])
    a = open_pairs(mesh_pairs)
    assert torch.allclose(b["prior"], _images(a.prior[ds.index[:3]]).float() * (2 / 255) - 1, atol=1e-6)
    compact = PairDataset(mesh_pairs, splits=("train", "val"), compact=True).__getitems__([0, 1, 2])
    assert compact["prior"].dtype == torch.uint8 and compact["prior"].shape == (3, 128, 128, 3)
    # The Digit's mirror swaps its red and green lights: the prior, like the tactile image, swaps them too.
    order = SENSORS.build({"name": "digit"}).mirror_channels()
    m = mirror_batch(b, order)
    assert torch.equal(m["prior"], b["prior"].flip(-1)[:, list(order)])


def test_prior_of_a_mirrored_crop_is_the_mirrored_prior():
    # The Digit's gel and lights are mirror images of each other up to a swap of red and green: what a mirrored
    # depth crop's press changes in the image is the mirrored change with those channels swapped (the
    # background, a photo of the untouched gel, is not mirrored).
    sensor, framing = _sensor_framing()
    prior = DepthPrior(sensor, {"name": "warp_gel"}, framing)
    y, x = torch.meshgrid(torch.linspace(-1, 1, 128), torch.linspace(-1, 1, 128), indexing="ij")
    bump = 0.5 + 0.05 * ((x - 0.3) ** 2 + (y + 0.2) ** 2)  # an off-centre dome, 2 mm per unit of 0.05
    depth = torch.stack([bump, bump + 0.01 * torch.sin(6 * x)])
    a = prior(depth.numpy(), 3.0)
    b = prior(depth.flip(-1).numpy(), 3.0)
    background = resize_uint8(sensor.background()).astype(int)
    change_a, change_b = a.astype(int) - background, b.astype(int) - background
    order = list(sensor.mirror_channels())
    assert np.abs(change_a).mean() > 3  # a real press
    assert np.abs(change_b - change_a[:, :, ::-1][..., order]).max() <= 2


def test_prior_needs_aligned_metric_crops():
    sensor, framing = _sensor_framing(crop_extent="footprint")
    with pytest.raises(TnfError, match="pair.crop_extent=sensor"):
        DepthPrior(sensor, {"name": "warp_gel"}, framing)
    sensor, framing = _sensor_framing()
    with pytest.raises(TnfError, match=r"depth crops must be \[B, 128, 128\]"):
        DepthPrior(sensor, {"name": "warp_gel"}, framing)(np.zeros((2, 64, 64)), 3.0)


def test_a_generator_that_takes_the_prior_names_what_makes_it(mesh_pairs):
    # Without pair.prior the batches have no prior: the error says which setting makes it.
    from tnf.registry import GENERATORS

    gen = GENERATORS.build({"name": "tn_cgan", "ngf": 8, "ndf": 8, "inputs": ["rgb", "background", "prior"],
                            "skips": ["background", "prior"]})  # fmt: skip
    batch = {k: v for k, v in PairDataset(mesh_pairs, splits=("train",)).__getitems__([0, 1]).items() if k != "prior"}
    with pytest.raises(TnfError, match="pair.prior=true"):
        gen.generate(batch)


def test_generate_feeds_a_prior_model_the_prior_of_its_renders(mesh_pairs):
    # Train a tiny model that adds its output to the prior, then generate novel touches of a scene with it:
    # each image is what the model makes of the rendered crops together with their prior, made as `tnf pair`
    # makes it.
    from tests.data.pair_inputs import SphereScene
    from tnf.artifacts import read_json
    from tnf.data.preprocess import gel_size_m
    from tnf.data.render import TouchItem, render_rgbd_crops
    from tnf.generators import load_generator
    from tnf.scenes import save_scene
    from tnf.stages import generate, train
    from tnf.testing import compose

    root = mesh_pairs.parents[1]
    base = [f"data_root={root}", "debug=tiny", "progress=false", "device=cpu", "data.batch_size=4"]
    model = ["generator.inputs=[rgb,depth_and_slope,background,prior]", "generator.skips=[depth_and_slope,prior]"]
    model += ["generator.residual_on=prior", "data.datasets=[digit-mesh]", "train.run_name=prior"]
    train.run(compose("train", [*base, *model, "train.epochs=1", "train.decay_epochs=0"]))
    save_scene(SphereScene(SphereScene.Config(radius=0.04)), root / "scenes" / "hashgrid" / "builtin" / "ball")
    gen = [*base, "object=ball", "generate.model=prior", "generate.n_poses=3", "generate.radius=0.1"]
    assert generate.run(compose("generate", gen))["written"] == {"ball": 3}
    # The prior's settings are part of what the images depend on: another force makes them again.
    assert generate.run(compose("generate", gen))["written"] == {}
    assert generate.run(compose("generate", [*gen, "touch.force=4.0"]))["written"] == {"ball": 3}
    assert generate.run(compose("generate", gen))["written"] == {"ball": 3}

    folder = root / "generated" / "prior" / "builtin" / "ball"
    item = TouchItem.load(folder)
    cfg = compose("generate", gen)
    sensor = SENSORS.build(cfg.sensor)
    pre = open_pairs(mesh_pairs).manifest["preprocess"]
    framing = Framing.from_settings({k: v for k, v in pre.items() if k not in ("crop_px", "size")}).with_sensor(sensor)
    cam = read_json(root / "capture" / "builtin" / "ball" / "transforms.json", "capture")
    c2w = torch.as_tensor(item.start_poses(), dtype=torch.float32)
    scene = SphereScene(SphereScene.Config(radius=0.04))
    rgb, depth, _, _ = render_rgbd_crops(scene, c2w, (cam["fl_x"], cam["fl_y"]), gel_size_m(sensor), framing)
    prior = DepthPrior(sensor, cfg.simulator, framing)(depth, float(cfg.touch.force))
    background = resize_uint8(sensor.background())[None].repeat(3, 0)
    unit = lambda x: _images(x).float() / 127.5 - 1  # noqa: E731
    batch = {"rgb": unit(rgb), "depth": torch.from_numpy(depth.astype(np.float32))[:, None] * 2 - 1}
    batch |= {"background": unit(background), "prior": unit(prior)}
    system = load_generator(root / "models" / "prior" / "best.ckpt", "cpu")
    with torch.no_grad():
        expect = ((system.generate(batch).clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8).permute(0, 2, 3, 1)
    images = np.stack([np.asarray(Image.open(folder / t.image)) for t in item.touches])
    assert np.abs(images.astype(int) - expect.numpy().astype(int)).max() <= 1
    # The prior shows a press here (the sphere is touched), and the model's images follow it.
    assert np.abs(prior.astype(int) - background.astype(int)).mean() > 2


def test_mixing_datasets_with_and_without_the_prior_serves_it_from_none(mesh_pairs, tmp_path):
    import shutil

    from tnf.artifacts import MANIFEST, read_json, write_json
    from tnf.data.dataset import MixedPairDataset

    plain = tmp_path / "plain"
    shutil.copytree(mesh_pairs, plain)
    (plain / "prior.npy").unlink()
    m = read_json(plain / MANIFEST, "manifest")
    write_json(plain / MANIFEST, {**m, "prior": None})
    both = MixedPairDataset([PairDataset(mesh_pairs), PairDataset(plain)])
    n = len(both.datasets[0])
    for rows in ([0, 1], [n, n + 1], [0, n]):  # from one dataset, the other, and both
        batch = both.__getitems__(rows)
        assert "prior" not in batch and batch["tactile"].shape == (2, 3, 128, 128)
    assert "prior" in MixedPairDataset([PairDataset(mesh_pairs), PairDataset(mesh_pairs)]).__getitems__([0, n])
