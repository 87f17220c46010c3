"""Preprocessing (crop on the centre ray, depth normalisation) and split assignment."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.data.pair_inputs import SphereScene, look_at
from tnf.data import SPLITS, assign_splits, choose_novel_objects, crop_for_sensor, preprocess_rgbd
from tnf.data.preprocess import contact_depth, gel_size_m
from tnf.data.render import Framing, render_rgbd_crops
from tnf.errors import TnfError
from tnf.registry import SENSORS


def coordinate_image(h: int, w: int) -> torch.Tensor:
    """[1, h, w, 3]: red = column / 255, green = row / 255."""
    v, u = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    return torch.stack([u / 255, v / 255, torch.zeros(h, w)], -1)[None].float()


def test_crop_is_centred_on_the_centre_ray():
    rgb = coordinate_image(80, 100)
    depth = torch.ones(1, 80, 100)
    out, _ = preprocess_rgbd(rgb, depth, None, crop_px=20, out=20, center=(30.0, 40.0))
    assert out.shape == (1, 20, 20, 3) and out.dtype == np.uint8
    assert out[0, 0, 0, 0] == 20 and out[0, 0, -1, 0] == 39  # columns 20..39 around cx = 30
    assert out[0, 0, 0, 1] == 30 and out[0, -1, 0, 1] == 49  # rows 30..49 around cy = 40
    out, _ = preprocess_rgbd(rgb, depth, None, crop_px=40, out=40)  # default: the image centre
    assert out[0, 0, 0, 0] == 30 and out[0, 0, 0, 1] == 20


def test_crop_larger_than_image_is_refused():
    with pytest.raises(TnfError, match="larger than"):
        preprocess_rgbd(torch.zeros(1, 32, 48, 3), torch.ones(1, 32, 48), None, crop_px=40)


def test_output_size_and_types():
    rgb, depth = preprocess_rgbd(torch.rand(3, 200, 240, 3), torch.rand(3, 200, 240) + 0.1, None, crop_px=150)
    assert rgb.shape == (3, 128, 128, 3) and rgb.dtype == np.uint8
    assert depth.shape == (3, 128, 128) and depth.dtype == np.float16
    assert depth.min() >= 0 and depth.max() <= 1


def test_depth_center_and_minmax_on_a_tilted_plane():
    # Plane: depth = 0.1 m + 1 mm per column from the centre; crop 16 px centred on column 16 of 32.
    u = torch.arange(32).float() + 0.5
    plane = (0.1 + 0.001 * (u - 16)).expand(1, 32, 32).clone()
    _, d = preprocess_rgbd(
        torch.zeros(1, 32, 32, 3), plane, torch.ones(1, 32, 32), crop_px=16, out=16, depth_window=0.04
    )
    d = d.astype(np.float32)[0]
    # Centre block (columns 15, 16 of the image = 7, 8 of the crop): nearest is column 15 at 0.0995 m.
    expect = 0.5 + (0.001 * (np.arange(8, 24) + 0.5 - 16) - (-0.0005)) / 0.04
    np.testing.assert_allclose(d[0], expect, atol=1e-3)
    _, d = preprocess_rgbd(torch.zeros(1, 32, 32, 3), plane, None, crop_px=16, out=16, depth_norm="minmax")
    np.testing.assert_allclose(d[0, 0].astype(np.float32), np.arange(16) / 15, atol=1e-3)


def test_depth_on_a_sphere_and_empty_pixels():
    r, dist, f, n = 0.04, 0.1, 50.0, 64
    scene = SphereScene(SphereScene.Config(radius=r))
    c2w = torch.tensor(look_at([0, 0, dist]), dtype=torch.float32)[None]
    out = scene.render_rgbd(c2w, torch.tensor([f, f, n / 2, n / 2]), n, n)
    _, d = preprocess_rgbd(out["rgb"], out["depth"], out["opacity"], crop_px=n, out=n, depth_window=0.04)
    d = d[0].astype(np.float32)
    near = dist - r
    # Centre 2x2 block: rays 0.5 px off axis; the value there is 0.5 by construction, the rest is relative.
    ray = np.array([0.5 / f, 0.5 / f, -1.0])
    t = _sphere_t(ray, dist, r)
    assert d[n // 2, n // 2] == pytest.approx(0.5, abs=1e-3)
    # A pixel 10 px right of the centre.
    ray10 = np.array([10.5 / f, -0.5 / f, -1.0])
    assert d[n // 2, n // 2 + 10] == pytest.approx(0.5 + (_sphere_t(ray10, dist, r) - t) / 0.04, abs=2e-3)
    assert d[0, 0] == 1.0 and d[-1, -1] == 1.0  # corners miss the sphere (angular radius 23.6 deg < 32.6)
    assert near < t < near + 1e-4
    _, mm = preprocess_rgbd(out["rgb"], out["depth"], out["opacity"], crop_px=n, out=n, depth_norm="minmax")
    mm = mm[0].astype(np.float32)
    hit = out["opacity"][0].numpy() > 0.5
    assert mm[hit].min() == pytest.approx(0, abs=1e-3) and mm[hit].max() == pytest.approx(1, abs=1e-3)
    assert (mm[~hit] == 1).all()


def _sphere_t(ray: np.ndarray, dist: float, r: float) -> float:
    """z-depth of the first hit of a camera ray (z-component -1) from (0, 0, dist) towards the origin."""
    o = np.array([0, 0, dist])
    a, b, c = ray @ ray, 2 * o @ ray, o @ o - r * r
    return (-b - math.sqrt(b * b - 4 * a * c)) / (2 * a)


def test_crop_for_sensor_matches_gel_footprint():
    sensor = SENSORS.build({"name": "digit"})  # 20 x 30 mm gel
    assert crop_for_sensor(sensor, (100.0, 100.0, 64, 64), distance=0.1) == 30  # 100 px * 0.03 m / 0.1 m
    assert crop_for_sensor(sensor, (100.0, 100.0, 64, 64), distance=0.1, margin=2) == 60
    with pytest.raises(TnfError):
        crop_for_sensor(sensor, (100.0, 100.0, 64, 64), distance=0)


def test_contact_depth_is_the_nearest_surface_inside_the_gel_footprint():
    # A wall 0.1 m away; a post 0.07 m away whose pixels lie 25 mm off the axis, outside a 20 x 30 mm gel;
    # a bump 0.09 m away, 8 mm off the axis (inside). Camera: 100 px focal, centre (32, 32).
    depth = torch.full((2, 64, 64), 0.1)
    k = torch.tensor([100.0, 100.0, 32.0, 32.0])
    depth[:, 30:34, 57:60] = 0.07  # (u + 0.5 - 32) / 100 * 0.07 > 0.0175 m
    depth[1, 30:34, 40:42] = 0.09  # 8.5-10 px * 0.09 / 100 = 7.7-9.5 mm < 10 mm
    assert contact_depth(depth, k, (0.02, 0.03)).tolist() == pytest.approx([0.1, 0.09])
    # A wider gel reaches the post; nothing at all in the footprint gives NaN.
    assert contact_depth(depth, k, (0.06, 0.03))[0] == pytest.approx(0.07)
    assert math.isnan(contact_depth(torch.zeros(1, 8, 8), k, (0.02, 0.03))[0])


@pytest.mark.parametrize("crop_distance", ["contact", "fixed"])
def test_contact_crops_keep_the_gel_scale_at_any_start_distance(crop_distance):
    # The same sphere point touched from start poses 0.1 and 0.16 m from its centre (first contact at 0.06 and
    # 0.12 m). Framed at the contact, both crops show the same 45 mm patch around it: the images agree. With
    # one fixed crop (the footprint at 0.09 m) the near one shows a smaller patch than the far one.
    scene = SphereScene(SphereScene.Config(0.04))
    framing = Framing(crop_distance=crop_distance, footprint_distance=0.09, crop_margin=1.5, depth_norm="contact")
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    c2w = torch.tensor(np.stack([look_at(axis * 0.1), look_at(axis * 0.16)]), dtype=torch.float32)
    rgb, depth, contact, _ = render_rgbd_crops(scene, c2w, (60.0, 60.0), (0.02, 0.03), framing)
    np.testing.assert_allclose(contact, [0.06, 0.12], atol=2e-4)
    # First contact at 0.5: the sphere's nearest point is on the axis.
    assert depth[:, 62:66, 62:66].astype(np.float32).min() == pytest.approx(0.5, abs=2e-3)
    hit = depth < 1
    both = hit[0] & hit[1]
    colour_change = np.abs(rgb[0].astype(int) - rgb[1].astype(int))[both].mean()
    if crop_distance == "contact":
        # The same surface patch in the same pixels (perspective alone moves the sphere's rim a little).
        assert abs(hit[0].mean() - hit[1].mean()) < 0.1 and colour_change < 5
    else:
        assert hit[1].mean() < 0.85 * hit[0].mean() and colour_change > 15


@pytest.mark.parametrize("extent", ["sensor", "footprint"])
def test_sensor_extent_crops_are_pixel_aligned_with_the_tactile_image(extent):
    # A 10 mm sphere pressed by a flat Digit whose axis passes 4 mm right of and 6 mm below its top: the
    # imprint lies off the tactile image's centre. Framed with crop_extent=sensor, the RGB-D crop shows the
    # sphere's top (where the gel presses in) at the same place as the imprint; the square footprint crop
    # (45 mm across, against the image's 19 x 25 mm) draws it nearer the centre.
    import trimesh

    from tnf.registry import SIMULATORS

    sensor = SENSORS.build({"name": "digit", "sag": 0.0, "noise_std": 0.0})
    sim = SIMULATORS.build({"name": "warp_gel"}, sensor=sensor, device="cpu")
    c2w = np.eye(4)
    c2w[:3, 3] = (-0.004, 0.006, 0.01 + 0.05)  # the sphere's top is at x = +4 mm, y = -6 mm in the sensor frame
    out = sim.press(trimesh.creation.icosphere(subdivisions=5, radius=0.01), c2w[None], 3.0)
    assert out.hit[0]
    rows, cols = np.nonzero(out.contact[0])
    imprint = ((cols.mean() + 0.5) / sensor.width, (rows.mean() + 0.5) / sensor.height)
    assert imprint[0] > 0.6 and imprint[1] > 0.6  # right of and below the centre

    framing = Framing(crop_distance="contact", footprint_distance=0.05, crop_extent=extent).with_sensor(sensor)
    assert (framing.view_size is not None) == (extent == "sensor")
    scene = SphereScene(SphereScene.Config(0.01))
    _, depth, contact, _ = render_rgbd_crops(
        scene, torch.tensor(c2w[None], dtype=torch.float32), (60.0, 60.0), gel_size_m(sensor), framing
    )
    assert contact[0] == pytest.approx(0.05, abs=1e-4)  # first contact: the sphere's top, 50 mm below
    # The sphere above the depth the gel was pushed to: the rigid-gel contact patch, centred on the same point.
    top = depth[0].astype(np.float32) < 0.5 + float(out.penetration[0]) / framing.depth_window
    r, c = np.nonzero(top)
    seen = ((c.mean() + 0.5) / 128, (r.mean() + 0.5) / 128)
    error_px = 128 * np.abs(np.subtract(seen, imprint)).max()
    if extent == "sensor":
        assert error_px < 1.5
    else:
        assert error_px > 10


def test_framing_settings():
    f = Framing.from_settings(
        {"crop_distance": "contact", "crop_px": None, "depth_norm": "contact"}, footprint_distance=0.1
    )
    assert f.per_view and f.crop_margin == 1.5
    assert Framing.from_settings({"crop_distance": "contact", "crop_px": 40}).per_view is False
    fixed = Framing.from_settings(
        {"crop_distance": "fixed", "footprint_distance": 0.1, "depth_norm": "center", "depth_window": 0.04}
    )
    assert fixed.crop_distance == "fixed" and fixed.fixed_crop((100.0, 100.0), (0.02, 0.03)) == 45
    with pytest.raises(TnfError, match="crop_distance"):
        Framing(crop_distance="median")
    with pytest.raises(TnfError, match="footprint distance"):
        Framing(footprint_distance=0.0)
    with pytest.raises(TnfError, match="crop_extent must be"):
        Framing(crop_extent="gel")
    with pytest.raises(TnfError, match="crop_distance=contact"):
        Framing(crop_distance="fixed", crop_extent="sensor")
    # A dataset's stored view size (a JSON list) comes back as the tuple it was, and the sensor does not replace it.
    f = Framing.from_settings({"crop_distance": "contact", "crop_extent": "sensor", "view_size": [0.02, 0.03]})
    assert f.view_size == (0.02, 0.03) and f.with_sensor(SENSORS.build({"name": "digit"})).view_size == (0.02, 0.03)


def test_novel_objects_by_config_and_seed():
    names = [f"o{i}" for i in range(27)]
    a = choose_novel_objects(names, None, 3, seed=0)
    assert len(a) == 3 and set(a) <= set(names)
    assert choose_novel_objects(list(reversed(names)), None, 3, seed=0) == a  # order of the list does not matter
    assert choose_novel_objects(names, None, 3, seed=1) != a
    assert choose_novel_objects(names, ["o5", "o1"], 3) == ["o1", "o5"]
    with pytest.raises(TnfError, match="nope"):
        choose_novel_objects(names, ["nope"])
    with pytest.raises(TnfError, match="only 2 objects"):
        choose_novel_objects(["a", "b"], None, 3)


def test_assign_splits_by_touch():
    labels = ["train", "val", "novel_view", "train"]
    assert [SPLITS[c] for c in assign_splits(labels, novel_object=False)] == labels
    assert {SPLITS[c] for c in assign_splits(labels, novel_object=True)} == {"novel_object"}
    with pytest.raises(TnfError, match="bogus"):
        assign_splits(["train", "bogus"], novel_object=False)
