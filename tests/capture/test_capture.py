"""Capture: camera poses, rendered RGB-D against ray casting, transforms.json round trip, the stage."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tnf.cameras import load_transforms, look_at
from tnf.capture import (
    CaptureConfig,
    camera_distance,
    camera_poses,
    capture_config,
    intrinsics,
    write_views,
)
from tnf.capture.render import MeshRenderer
from tnf.errors import TnfError
from tnf.objects.builtin import MAKERS, Builtin


def test_poses_look_at_the_object_and_are_rotations():
    cfg = CaptureConfig(num_views=48, num_test_views=8)
    train, test = camera_poses(0.1, cfg, seed=0)
    assert train.shape == (48, 4, 4) and test.shape == (8, 4, 4)
    for m in np.concatenate([train, test]):
        r, t = m[:3, :3], m[:3, 3]
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
        assert np.isclose(np.linalg.det(r), 1)
        # -z (the viewing direction) points at the origin.
        np.testing.assert_allclose(-r[:, 2], -t / np.linalg.norm(t), atol=1e-9)
    dirs = train[:, :3, 3] / np.linalg.norm(train[:, :3, 3], axis=1, keepdims=True)
    assert abs(dirs.mean(0)).max() < 0.05  # evenly spread over the sphere
    assert not np.isin(np.round(test[:, :3, 3], 6), np.round(train[:, :3, 3], 6)).all(1).any()
    hemi = CaptureConfig(views="hemisphere", num_views=30, min_elevation_deg=10, max_elevation_deg=60)
    h, _ = camera_poses(0.1, hemi, seed=1)
    el = np.degrees(np.arcsin(h[:, 2, 3] / np.linalg.norm(h[:, :3, 3], axis=1)))
    assert el.min() >= 10 - 1e-6 and el.max() <= 60 + 1e-6


def test_capture_config_rejects_bad_values():
    assert capture_config({"resolution": 64}).resolution == 64
    with pytest.raises(TnfError, match="capture: unknown key 'res'"):
        capture_config({"res": 64})
    with pytest.raises(TnfError, match="fov_deg"):
        capture_config({"fov_deg": 0.5})
    with pytest.raises(TnfError, match="antialias"):
        capture_config({"antialias": -1})


def _raycast_depth(mesh, c2w, k, w, h):
    fx, fy, cx, cy = k
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d_cam = np.stack([(j - cx) / fx, -(i - cy) / fy, -np.ones_like(j)], -1).reshape(-1, 3)
    d_world = d_cam @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], d_world.shape)
    locs, idx, _ = mesh.ray.intersects_location(origins, d_world, multiple_hits=False)
    depth = np.zeros(w * h)
    depth[idx] = (locs - c2w[:3, 3]) @ (-c2w[:3, 2])
    return depth.reshape(h, w)


@pytest.mark.parametrize("antialias", [0, 4])
def test_depth_agrees_with_ray_casting_at_pixel_centres(antialias):
    # Off-centre principal point and unequal focal lengths pin the pixel convention: a half-pixel shift of
    # either axis would put depth edges and slanted surfaces a millimetre off.
    mesh = Builtin().load("mug")
    cfg = CaptureConfig(resolution=40, num_views=2, num_test_views=0)
    radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
    poses, _ = camera_poses(radius, cfg)
    fx, fy, cx, cy = intrinsics(cfg)
    k = (fx, 1.1 * fy, cx - 3.3, cy + 2.2)
    r = MeshRenderer(mesh, 40, 40, antialias=antialias)
    rgb, depth = r.render(poses, k)
    r.close()
    assert rgb.shape == (2, 40, 40, 3) and rgb.dtype == np.uint8 and depth.dtype == np.float32
    for pose, d in zip(poses, depth):
        ref = _raycast_depth(mesh, pose, k, 40, 40)
        both = (ref > 0) & (d > 0)
        assert (ref > 0).sum() > 100
        # Depth is sampled at the same points as the rays: masks agree but for a ray grazing an edge, and
        # depth agrees to the 24-bit depth buffer's precision (~1e-6 m here; a pixel's footprint is ~2 mm).
        assert ((ref > 0) != (d > 0)).sum() <= 2
        err = np.abs(d[both] - ref[both])
        assert np.median(err) < 1e-5 and (err < 1e-4).mean() > 0.99


def test_one_renderer_for_many_objects_and_renderers_independent():
    cfg = CaptureConfig(resolution=24, num_views=3, num_test_views=0)
    k = intrinsics(cfg)
    ball, box = Builtin().load("ball"), Builtin().load("box")
    poses, _ = camera_poses(float(np.linalg.norm(box.vertices, axis=1).max()), cfg)
    a = MeshRenderer(ball, 24, 24)
    b = MeshRenderer(box, 24, 24)
    rgb_ball, depth_ball = a.render(poses, k)
    a.set_mesh(box)
    rgb_a, depth_a = a.render(poses, k)
    rgb_b, depth_b = b.render(poses, k)
    np.testing.assert_array_equal(depth_a, depth_b)  # swapping the mesh leaves nothing of the old one
    np.testing.assert_array_equal(rgb_a, rgb_b)
    assert not np.array_equal(depth_a > 0, depth_ball > 0)
    # Closing one renderer leaves the others working (pyrender's own delete terminates the shared display).
    b.close()
    _, again = a.render(poses, k)
    np.testing.assert_array_equal(again, depth_a)
    a.close()
    with pytest.raises(RuntimeError, match="after close"):
        a.render(poses, k)


def test_capture_object_writes_every_view(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    from tnf.capture.render import capture_object

    cfg = CaptureConfig(resolution=24, num_views=5, num_test_views=3)
    mesh = Builtin().load("can")
    train, test = camera_poses(float(np.linalg.norm(mesh.vertices, axis=1).max()), cfg)
    r = MeshRenderer(mesh, 24, 24)
    with ThreadPoolExecutor(2) as pool:
        coverage = capture_object(r, tmp_path, train, test, cfg, pool, chunk=2)
    rgb, depth = r.render(train, intrinsics(cfg))
    r.close()
    images, c2w, k, w, h, d = load_transforms(tmp_path)
    np.testing.assert_array_equal(images[..., :3], rgb)  # every view in order, as rendered in one batch
    np.testing.assert_array_equal(d, depth)
    np.testing.assert_array_equal(images[..., 3] == 255, depth > 0)
    np.testing.assert_allclose(c2w, train, atol=1e-6)
    assert coverage == pytest.approx(float((depth > 0).mean()))
    assert load_transforms(tmp_path / "transforms_test.json")[0].shape == (3, 24, 24, 4)


def test_object_fills_a_sensible_part_of_the_frame():
    mesh = Builtin().load("can")
    cfg = CaptureConfig(resolution=32, num_views=8, num_test_views=0)
    poses, _ = camera_poses(float(np.linalg.norm(mesh.vertices, axis=1).max()), cfg)
    _, depth = MeshRenderer(mesh, 32, 32).render(poses, intrinsics(cfg))
    for d in depth:
        mask = d > 0
        assert 0.1 < mask.mean() < 0.8
        assert not mask[0].any() and not mask[-1].any() and not mask[:, 0].any() and not mask[:, -1].any()
        ys, xs = np.nonzero(mask)
        assert abs(ys.mean() - 15.5) < 5 and abs(xs.mean() - 15.5) < 5


@pytest.mark.slow  # ~40 s: one renderer per object
def test_every_builtin_object_renders():
    cfg = CaptureConfig(resolution=32)
    means = {}
    for name in sorted(MAKERS):
        mesh = Builtin().load(name)
        radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
        pose = look_at(np.array([0.5, -0.6, 0.62]) * camera_distance(radius, cfg))
        r = MeshRenderer(mesh, 32, 32)
        rgb, depth = r.render(pose, intrinsics(cfg))
        r.close()
        assert (depth > 0).sum() >= 10, name  # the pencil is 1 cm thin
        means[name] = rgb[0][depth[0] > 0].mean(0)
    # Objects look different: not all the same colour.
    assert np.std(np.stack(list(means.values())), axis=0).max() > 20


def test_transforms_round_trip_and_errors(tmp_path):
    cfg = CaptureConfig(resolution=16, num_views=4, num_test_views=2)
    train, test = camera_poses(0.05, cfg)
    rgb = np.random.default_rng(0).integers(0, 255, (4, 16, 16, 3), dtype=np.uint8)
    depth = np.zeros((4, 16, 16), np.float32)
    depth[:, 4:12, 4:12] = 0.3
    write_views(tmp_path, "train", train, rgb, depth, cfg)
    images, c2w, k, w, h, d = load_transforms(tmp_path)
    assert images.shape == (4, 16, 16, 4) and (w, h) == (16, 16)
    np.testing.assert_array_equal(images[..., :3], rgb)
    np.testing.assert_array_equal(images[..., 3] > 0, depth > 0)
    np.testing.assert_allclose(c2w, train, atol=1e-6)
    np.testing.assert_allclose(k, intrinsics(cfg))
    np.testing.assert_array_equal(d, depth)

    meta = json.loads((tmp_path / "transforms.json").read_text())
    bad = tmp_path / "bad.json"
    for edit, msg in [
        (lambda m: m.pop("w"), "missing key 'w'"),
        (
            lambda m: m["frames"][1].__setitem__("transform_matrix", [[1, 0, 0]]),
            "shape \\[1, 3\\], expected \\[4, 4\\]",
        ),
        (lambda m: m["frames"][0].__setitem__("file_path", "images/none.png"), "image not found"),
        (lambda m: m.__setitem__("h", 20), "image is 16x16, transforms file says 16x20"),
        (lambda m: (m.pop("fl_x"), m.pop("camera_angle_x")), "focal length"),
    ]:
        m = json.loads(json.dumps(meta))
        edit(m)
        bad.write_text(json.dumps(m))
        with pytest.raises(TnfError, match=msg):
            load_transforms(bad)
    from PIL import Image

    Image.fromarray(np.zeros((16, 16), np.uint8), "L").save(tmp_path / "images" / "train_000.png")
    with pytest.raises(TnfError, match="expected an RGB or RGBA image"):
        load_transforms(tmp_path / "transforms.json")
    with pytest.raises(TnfError, match="transforms file not found"):
        load_transforms(tmp_path / "nope.json")


def test_mesh_scene_renders_like_the_capture():
    from tnf.registry import SCENES
    from tnf.scenes.mesh import MeshScene

    mesh = Builtin().load("ball")
    scene = MeshScene.from_mesh(mesh)
    assert SCENES.get("mesh") is MeshScene
    cfg = CaptureConfig(resolution=24)
    poses = torch.from_numpy(camera_poses(0.04, CaptureConfig(num_views=2, num_test_views=0))[0]).float()
    k = torch.tensor(intrinsics(cfg))
    out = scene.render_rgbd(poses, k, 24, 24)
    assert out["rgb"].shape == (2, 24, 24, 3) and out["depth"].shape == (2, 24, 24)
    assert out["rgb"].dtype == torch.float32 and 0 <= out["rgb"].min() and out["rgb"].max() <= 1
    _, ref = MeshRenderer(mesh, 24, 24).render(poses.double().numpy(), intrinsics(cfg))
    np.testing.assert_allclose(out["depth"].numpy(), ref, atol=1e-5)
    assert torch.equal(out["opacity"] > 0, out["depth"] > 0)


def test_capture_stage_writes_and_skips(data_root, capsys):
    from tnf.cli import main

    args = ["capture", "debug=tiny", "progress=false", "capture.resolution=32", "capture.num_views=6"]
    assert main(args) == 0
    for obj in ("ball", "box"):
        folder = data_root / "capture" / "builtin" / obj
        images, c2w, k, w, h, depth = load_transforms(folder / "transforms.json")
        assert images.shape == (6, 32, 32, 4) and depth.shape == (6, 32, 32)
        assert (depth > 0).any() and np.array_equal(images[..., 3] > 0, depth > 0)
        test = load_transforms(folder / "transforms_test.json")
        assert test[0].shape[0] == 4
        assert (
            json.loads((folder / "manifest.json").read_text())["info"]["num_views"] == 6
            if "info" in json.loads((folder / "manifest.json").read_text())
            else json.loads((folder / "manifest.json").read_text())["num_views"] == 6
        )
    capsys.readouterr()
    assert main(args) == 0
    assert capsys.readouterr().out.count("skipped (done)") == 2
    assert main(["capture", "object=nope"]) == 1
