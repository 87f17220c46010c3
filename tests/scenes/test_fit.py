"""Fitting a small hash grid on the CPU to an analytic sphere: it learns, saves, loads, resumes."""

import json
import resource

import pytest
import torch

from tests.scenes.stops import Stop, stop_at
from tnf.cameras import camera_rays, look_at, read_views
from tnf.errors import TnfError
from tnf.scenes import load_scene, save_scene
from tnf.scenes.fit import build_scene, evaluate_scene, fit_object, fit_scene, psnr
from tnf.scenes.synthetic import render_sphere, sphere_poses, write_sphere_dataset
from tnf.scenes.system import FitSettings

TINY = {
    "name": "hashgrid",
    "levels": 4,
    "log2_table_size": 12,
    "base_resolution": 8,
    "max_resolution": 48,
    "hidden": 16,
    "samples_per_ray": 48,
    "occupancy_resolution": 16,
    "occupancy_update_every": 8,
    "occupancy_warmup": 16,
}
SETTINGS = FitSettings(steps=120, batch_rays=256, lr=2e-2, log_every=20, checkpoint_every=40)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_sphere_dataset(tmp_path_factory.mktemp("sphere"), n_train=10, n_test=2, size=24)


@pytest.fixture(scope="module")
def fitted(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit")
    torch.manual_seed(0)
    before = evaluate_scene(
        build_scene(TINY, read_views(dataset / "transforms.json")),
        read_views(dataset / "transforms_test.json"),
        None,
        0.1,
    )
    metrics = fit_object(TINY, dataset, out, SETTINGS, seed=0)
    return out, before["metrics"], metrics


def test_fit_improves_psnr_and_depth(fitted):
    out, before, after = fitted
    assert after["psnr"] > before["psnr"] + 3.0, (before["psnr"], after["psnr"])
    # At 24 px and 120 steps the median depth error falls from about 31 mm to 14-17 mm (17 with the
    # visual-hull carving of the default settings, which halves the fitting time).
    assert after["depth_error_median_m"] < 0.6 * before["depth_error_median_m"]
    assert after["train_log"][-1]["loss"] < after["train_log"][0]["loss"]
    on_disk = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "depth_error_median_m", "depth_error_median_rel", "train_seconds", "steps"):
        assert key in on_disk, key
    assert on_disk["steps"] == SETTINGS.steps
    assert (out / "preview.png").is_file()


def test_checkpoint_round_trip(fitted, tmp_path):
    out, _, _ = fitted
    scene = load_scene(out)
    c2w = torch.tensor(look_at(torch.tensor([0.15, -0.1, 0.1]).numpy()), dtype=torch.float32)[None]
    k = torch.tensor([20.0, 20.0, 8.0, 8.0])
    a = scene.render_rgbd(c2w, k, 16, 16)
    again = load_scene(save_scene(scene, tmp_path / "copy.pt"))
    b = again.render_rgbd(c2w, k, 16, 16)
    for key in ("rgb", "depth", "opacity"):
        assert torch.equal(a[key], b[key]), key
    assert torch.equal(scene.occupied, again.occupied)


def test_renders_a_pose_outside_the_training_set(fitted):
    out, _, _ = fitted
    scene = load_scene(out)
    # Closer than any training camera, from an oblique direction, with another image size.
    eye = torch.tensor([0.09, 0.08, -0.06]).numpy()
    c2w = look_at(eye)
    gt, gt_depth = render_sphere(c2w, 30.0, 30.0, 10.0, 8.0, 20, 16, 0.05)
    r = scene.render_rgbd(torch.tensor(c2w, dtype=torch.float32), torch.tensor([30.0, 30.0, 10.0, 8.0]), 20, 16)
    assert r["rgb"].shape == (1, 16, 20, 3)
    hit = torch.from_numpy(gt_depth) > 0
    # The sphere covers the middle of the image: the scene sees it there at about the right depth.
    assert r["opacity"][0][hit].mean() > 0.7
    err = (r["depth"][0][hit] - torch.from_numpy(gt_depth)[hit]).abs().median()
    assert err < 0.025, err  # 2.5 cm: a quarter of the sphere's size, after 120 steps on 24 px images


def test_resume_continues_from_the_checkpoint(dataset, tmp_path):
    views = read_views(dataset / "transforms.json")
    resume = tmp_path / "resume.pt"
    settings = FitSettings(steps=12, batch_rays=64, checkpoint_every=5, log_every=1)
    torch.manual_seed(0)
    scene = build_scene(TINY, views)
    with pytest.raises(Stop):
        fit_scene(scene, views, settings, "hashgrid", resume_path=resume, on_step=stop_at(7))
    assert resume.is_file()
    steps = []
    torch.manual_seed(0)
    fresh = build_scene(TINY, views)
    info = fit_scene(fresh, views, settings, "hashgrid", resume_path=resume, on_step=lambda s, loss: steps.append(s))
    assert steps[0] == 5 and steps[-1] == 11 and info["steps"] == 12
    assert not resume.exists()


def test_resumed_fit_equals_an_uninterrupted_fit(dataset, tmp_path):
    # Each step's draws (ray batch, backgrounds, the scene's sampling) depend only on (seed, step), and the
    # checkpoint holds the optimiser and scheduler state: the resumed fit ends bit for bit where the other does.
    views = read_views(dataset / "transforms.json")
    settings = FitSettings(steps=20, batch_rays=64, checkpoint_every=8, log_every=3, distortion_weight=0.01)
    torch.manual_seed(0)
    whole = build_scene(TINY, views)
    ref = fit_scene(whole, views, settings, "hashgrid", resume_path=tmp_path / "whole.pt", seed=5)
    resume = tmp_path / "parts.pt"
    for stop in (10, 17):  # stopped twice: after the checkpoint of step 8, then after that of step 16
        torch.manual_seed(0)
        with pytest.raises(Stop):
            fit_scene(
                build_scene(TINY, views),
                views,
                settings,
                "hashgrid",
                resume_path=resume,
                on_step=stop_at(stop),
                seed=5,
            )
        assert resume.is_file()
    torch.manual_seed(1)  # the scene's initial weights come from the checkpoint, not from this
    parts = build_scene(TINY, views)
    info = fit_scene(parts, views, settings, "hashgrid", resume_path=resume, seed=5)
    a, b = whole.state_dict(), parts.state_dict()
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert info["log"] == ref["log"] and info["final_loss"] == ref["final_loss"]
    assert not resume.exists()


def test_non_finite_loss_stops_the_fit_naming_the_step(dataset, tmp_path):
    views = read_views(dataset / "transforms.json")
    settings = FitSettings(steps=30, batch_rays=64, checkpoint_every=10, log_every=5)
    resume = tmp_path / "resume.pt"
    torch.manual_seed(0)
    scene = build_scene(TINY, views)

    def poison(step, loss):
        if step == 12:  # the loss of step 13 is the first NaN
            with torch.no_grad():
                scene.encoding.table.fill_(float("nan"))

    with pytest.raises(TnfError, match=r"non-finite scene fitting loss \(NaN or Inf\) at step 13;"):
        fit_scene(scene, views, settings, "hashgrid", resume_path=resume, on_step=poison)
    # Caught at step 15 (a logged step), before the checkpoint of step 20 could overwrite the good one.
    assert torch.load(resume, weights_only=True)["global_step"] == 10


def test_a_checkpoint_of_other_settings_is_not_resumed_from(dataset, tmp_path, caplog):
    views = read_views(dataset / "transforms.json")
    resume = tmp_path / "resume.pt"
    settings = FitSettings(steps=12, batch_rays=64, checkpoint_every=5)
    with pytest.raises(Stop):
        fit_scene(build_scene(TINY, views), views, settings, "hashgrid", resume_path=resume, on_step=stop_at(7))
    steps = []
    other = FitSettings(steps=12, batch_rays=64, checkpoint_every=5, lr=1e-3)
    fit_scene(
        build_scene(TINY, views), views, other, "hashgrid", resume_path=resume, on_step=lambda s, loss: steps.append(s)
    )
    assert steps == list(range(12))
    assert "other settings" in caplog.text and not resume.exists()


def test_cpu_memory_of_a_tiny_fit_is_small(fitted):
    # Peak resident memory of this whole test process (torch included), in GiB.
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20 < 2.0


def test_load_scene_rejects_other_files(tmp_path):
    bad = tmp_path / "scene.pt"
    torch.save({"format": "tnf-scene", "version": 1, "name": "no_such_kind", "config": {}, "state": {}}, bad)
    with pytest.raises(TnfError, match="unknown scene kind"):
        load_scene(tmp_path)
    torch.save({"weights": torch.zeros(2)}, bad)
    with pytest.raises(TnfError, match="not a tnf scene"):
        load_scene(bad)
    with pytest.raises(TnfError, match="not found"):
        load_scene(tmp_path / "missing")


def test_carving_keeps_the_object_and_removes_seen_empty_space(dataset):
    views = read_views(dataset / "transforms.json")
    scene = build_scene({**TINY, "bound": 0.1}, views)
    kept = scene.carve(*views.cameras(), views.rgba()[..., 3])
    G = TINY["occupancy_resolution"]
    ar = (torch.arange(G) + 0.5) / G * 0.2 - 0.1
    centres = torch.stack(torch.meshgrid(ar, ar, ar, indexing="ij"), dim=-1).reshape(-1, 3)
    r = centres.norm(dim=-1)
    # every cell inside the sphere (radius 0.05 m) survives; most cells well outside it are carved away
    assert scene.hull[r < 0.045].all()
    assert scene.hull[r > 0.08].float().mean() < 0.2
    assert 0.0 < kept < 0.5


def _dense_and_marched(scene, c2w, k, w, h):
    """The reference (Eq. 1 over every sample the occupancy grid keeps, the differentiable pass) and the
    renderer's early-terminating march, both as z-depth images."""
    o, d, z = camera_rays(c2w, k, w, h)
    with torch.enable_grad():
        dense = scene.render_rays(o.reshape(-1, 3), d.reshape(-1, 3))
    dense = {key: dense[key].detach().reshape(-1, h, w, *dense[key].shape[1:]) for key in ("rgb", "depth", "opacity")}
    dense["depth"] = dense["depth"] * z
    return dense, scene.render_rgbd(c2w, k, w, h)


@pytest.mark.parametrize("kernel", [False, True], ids=["pytorch-march", "warp-march"])
def test_fast_render_equals_the_dense_quadrature(fitted, kernel):
    out, _, _ = fitted
    scene = load_scene(out)
    scene.march_kernel = kernel
    c2w = torch.tensor(sphere_poses(3, 0.2, offset=0.3), dtype=torch.float32)
    k = torch.tensor([28.0, 28.0, 12.0, 12.0])
    dense, fast = _dense_and_marched(scene, c2w, k, 24, 24)
    assert (fast["opacity"] > 0.5).float().mean() > 0.2  # the object is in view
    # The march drops only light below the termination threshold (1e-4 of it).
    assert (fast["rgb"] - dense["rgb"]).abs().max() < 1e-3
    assert (fast["opacity"] - dense["opacity"]).abs().max() < 1e-3
    assert (fast["depth"] - dense["depth"]).abs().max() < 1e-4  # metres


@pytest.mark.parametrize("kernel", [False, True], ids=["pytorch-march", "warp-march"])
def test_march_rounds_do_not_change_the_image(fitted, kernel):
    out, _, _ = fitted
    scene = load_scene(out)
    scene.march_kernel = kernel
    c2w = torch.tensor(sphere_poses(2, 0.2, offset=0.7), dtype=torch.float32)
    k = torch.tensor([28.0, 28.0, 12.0, 12.0])
    one = scene.render_rgbd(c2w, k, 24, 24)
    # Many small rounds (windows of 8 samples, 2 network samples each) and small chunks.
    scene.march_window, scene.march_samples, scene.march_budget = 8, 2, 0
    rounds = scene.render_rgbd(c2w, k, 24, 24, chunk=100)
    # A ray stops at the end of the round in which it turned opaque: smaller rounds stop it sooner, dropping
    # at most min_transmittance of its light (1e-4), never more.
    for key in ("rgb", "opacity"):
        assert (one[key] - rounds[key]).abs().max() <= scene.min_transmittance, key
    assert (one["depth"] - rounds["depth"]).abs().max() < 1e-5  # metres


def test_warp_march_selects_the_samples_of_the_pytorch_march(fitted):
    """The Warp selection looks as far along a ray as it needs, the PyTorch one a window at a time: the
    same samples are composited in the same order, so the images agree to float rounding."""
    out, _, _ = fitted
    scene = load_scene(out)
    c2w = torch.tensor(sphere_poses(3, 0.2, offset=0.45), dtype=torch.float32)
    k = torch.tensor([28.0, 28.0, 12.0, 12.0])
    images, samples = [], []
    for kernel in (False, True):
        scene.march_kernel = kernel
        scene.march_stats.update({key: 0 for key in scene.march_stats})
        images.append(scene.render_rgbd(c2w, k, 24, 24))
        samples.append(scene.march_stats["samples"])
    assert (images[0]["opacity"] > 0.5).float().mean() > 0.2  # the object is in view
    # Rounds can split a ray's samples differently (the window caps the PyTorch rounds), so the samples sent
    # past the point where a ray turned opaque may differ a little.
    assert samples[0] > 0 and abs(samples[1] - samples[0]) <= 0.1 * samples[0]
    for key in ("rgb", "depth", "opacity"):
        assert torch.allclose(images[0][key], images[1][key], atol=1e-5), key


def test_half_precision_render_is_close_to_float32(fitted):
    out, _, _ = fitted
    scene = load_scene(out)
    c2w = torch.tensor(sphere_poses(2, 0.2, offset=0.1), dtype=torch.float32)
    k = torch.tensor([28.0, 28.0, 12.0, 12.0])
    full = scene.render_rgbd(c2w, k, 24, 24)
    scene.render_half = True  # the CUDA default, forced on the CPU
    half = scene.render_rgbd(c2w, k, 24, 24)
    assert float(psnr(half["rgb"], full["rgb"]).min()) > 40.0
    both = (full["opacity"] > 0.5) & (half["opacity"] > 0.5)
    assert (half["depth"][both] - full["depth"][both]).abs().median() < 2e-4  # metres


def test_distortion_loss_starts_at_its_fraction_of_the_steps(dataset):
    # Each step's draws depend only on (seed, step): until distortion_start the fit is the colour-only fit,
    # bit for bit; from that step on the distortion term changes the loss.
    views = read_views(dataset / "transforms.json")

    def losses(**kw):
        out: list[float] = []
        torch.manual_seed(0)
        settings = FitSettings(steps=12, batch_rays=64, checkpoint_every=0, log_every=1, **kw)
        fit_scene(build_scene(TINY, views), views, settings, "hashgrid", on_step=lambda s, loss: out.append(loss))
        return out

    colour = losses(distortion_weight=0.0)
    late = losses(distortion_weight=1.0, distortion_start=0.5)
    assert late[:6] == colour[:6]
    assert all(a != b for a, b in zip(late[6:], colour[6:]))
    with pytest.raises(ValueError, match="distortion_start"):
        FitSettings(distortion_start=1.0).validate()
