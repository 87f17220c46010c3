"""Generated touches of real indenter presses: the sphere rendered as RGB-D at each press's pose, a trained
generator's images of them, and their realism against the real frames.

The press pose mirrors a touch of the pairing stage (``tnf.data.render``): the camera has the sensor's pose and
looks along its axis (-z) at a sphere of the indenter's radius, a mesh scene (``scene=mesh``). The sphere's
lowest point lies under the press's centre pixel: at the gel point ``Sensor.gel_grid`` gives that pixel, as
``tnf.real.presses.sphere_gaps`` places it for the simulator. The camera starts at the reference distance of
the generator's training data (the touches' median first contact, ``Framing.footprint_distance``) and advances
by the press's depth. The crop and depth normalisation are the training dataset's (``Framing``), through
``render_rgbd_crops``.

How the press's depth reaches the generator (``reference``):

- ``contact``: as in the pairing stage, depth is measured from where the gel first meets the surface (0.5
  there). A touch's own depth never reaches the input then: every press of one centre gives one input.
- ``gel``: depth is measured from the pressed gel's plane, ``depth`` beyond the first contact: the sphere's
  lowest point reads ``0.5 - depth / depth_window``, so a deeper press comes closer.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tnf.artifacts import MANIFEST, read_json
from tnf.data.preprocess import SIZE, gel_size_m, resize_uint8
from tnf.data.render import Framing, render_rgbd_crops
from tnf.errors import TnfError
from tnf.real.presses import SensorPresses
from tnf.sensors.base import Sensor

REFERENCES = ("gel", "contact")
"""Where the depth channel's 0.5 lies for a press (module docstring)."""
INDENTER_COLOUR = (0.72, 0.74, 0.76)
"""RGB in [0, 1] of the rendered indenter (a steel bearing ball)."""
PRESS_LESS_INPUTS = ("prior", "surface")
"""Generator inputs that presses do not give: the simulator's prior image and surface points (nor a force)."""


@dataclass
class PressRGBD:
    """RGB-D crops of presses, as a paired dataset stores them."""

    rgb: np.ndarray
    """``[N, 128, 128, 3]`` uint8."""
    depth: np.ndarray
    """``[N, 128, 128]`` float16 in [0, 1] (1: no surface)."""
    c2w: np.ndarray
    """``[N, 4, 4]`` camera-to-world poses, metres, the sphere's centre at the origin."""
    pixels: np.ndarray
    """``[N, 2]`` float ``(column, row)`` of each press's centre in the crop's 128 px (pixel centres at whole
    numbers)."""


def indenter_scene(radius_m: float, device: str = "cpu", subdivisions: int = 5) -> Any:
    """A ``mesh`` scene of a sphere of ``radius_m`` metres centred at the origin (an icosphere, steel grey)."""
    from tnf.objects.modelling import paint, sphere
    from tnf.registry import SCENES

    if not (math.isfinite(radius_m) and radius_m > 0):
        raise TnfError(f"indenter radius must be > 0 metres, got {radius_m}")
    mesh = paint(sphere(radius_m, subdivisions=subdivisions), lambda v: np.asarray(INDENTER_COLOUR))
    return SCENES.get("mesh").from_mesh(mesh).to(device)


def press_poses(sensor: Sensor, centers: np.ndarray, radius_m: float, distances: np.ndarray) -> np.ndarray:
    """``[N, 4, 4]`` sensor poses (camera-to-world, OpenGL) over a sphere of ``radius_m`` at the origin: the
    sensor looks along world -z, the sphere's lowest point faces each centre ``(column, row)`` (sensor pixels)
    at ``distances`` ``[N]`` metres from the camera."""
    fx, fy, cx, cy = sensor.intrinsics()
    d = sensor.cfg.camera_distance
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    x0 = (c[:, 0] + 0.5 - cx) / fx * d
    y0 = -(c[:, 1] + 0.5 - cy) / fy * d
    poses = np.tile(np.eye(4), (len(c), 1, 1))
    poses[:, 0, 3] = -x0
    poses[:, 1, 3] = -y0
    poses[:, 2, 3] = radius_m + np.asarray(distances, dtype=np.float64)
    return poses


def crop_pixels(sensor: Sensor, framing: Framing, centers: np.ndarray) -> np.ndarray:
    """``[N, 2]`` ``(column, row)`` in the 128 px RGB-D crop of the gel points under sensor pixels ``centers``
    (per-view framings: the crop spans the footprint, or the sensor's view, at the contact depth)."""
    fx, fy, cx, cy = sensor.intrinsics()
    d = sensor.cfg.camera_distance
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    x0 = (c[:, 0] + 0.5 - cx) / fx * d
    y0 = -(c[:, 1] + 0.5 - cy) / fy * d
    if framing.crop_extent == "sensor":
        w, h = framing.with_sensor(sensor).view_size or sensor.view_size()
    else:
        gw, gh = gel_size_m(sensor)
        w = h = framing.crop_margin * max(gw, gh)
    return np.stack([SIZE * (0.5 + x0 / w) - 0.5, SIZE * (0.5 - y0 / h) - 0.5], axis=1)


def press_rgbd(
    sensor: Sensor,
    sp: SensorPresses,
    radius_m: float,
    depth_scale: float = 1.0,
    *,
    framing: Framing | None = None,
    reference: str = "gel",
    device: str = "cpu",
    batch: int = 32,
) -> PressRGBD:
    """Render the indenter as RGB-D at each press's pose, preprocessed as the pairing stage preprocesses a touch.

    Args:
        sensor: the sensor of the presses (its pixel geometry places the sphere; its gel size frames the crop).
        sp: presses at the sensor's size (``at_sensor_size``): centres in sensor pixels, depths in metres.
        radius_m: the indenter's radius, metres.
        depth_scale: factor on each press's depth (the calibration's depth factor).
        framing: the crop and depth settings of the generator's training data (``checkpoint_framing``);
            default ``Framing()`` (the ``pair`` section's defaults). Crops sized per view only.
        reference: ``gel`` or ``contact``: where depth 0.5 lies (module docstring).
        device: torch device to render on.
        batch: presses rendered at once.

    Returns:
        ``PressRGBD``: ``rgb`` uint8 [N, 128, 128, 3], ``depth`` float16 [N, 128, 128], the poses and each
        press centre's crop pixel.
    """
    import torch

    if reference not in REFERENCES:
        raise TnfError(f"reference must be one of {', '.join(REFERENCES)}, got {reference!r}")
    if not (math.isfinite(depth_scale) and depth_scale > 0):
        raise TnfError(f"depth_scale must be > 0, got {depth_scale}")
    framing = (framing or Framing()).with_sensor(sensor)
    if not framing.per_view:
        raise TnfError(
            "presses are framed per view (pair.crop_distance=contact, no crop_px); this generator's data used "
            f"crop_distance={framing.crop_distance}, crop_px={framing.crop_px}"
        )
    depths = np.asarray(sp.depths, dtype=np.float64) * depth_scale
    if np.any(depths >= radius_m):
        deepest = depths.max() * 1e3
        raise TnfError(f"a press depth of {deepest:.3f} mm reaches the indenter's radius {radius_m * 1e3:g} mm")
    distance = float(framing.footprint_distance)
    if np.any(depths >= distance):
        raise TnfError(f"a press depth of {depths.max() * 1e3:.3f} mm is not smaller than the camera's distance")
    poses = press_poses(sensor, sp.centers, radius_m, distance - depths)
    scene = indenter_scene(radius_m, device)
    fx = sensor.intrinsics()[0]  # a per-view crop is set by the gel's size; the focal length cancels
    gel = gel_size_m(sensor)
    rgb = np.empty((len(poses), SIZE, SIZE, 3), np.uint8)
    depth = np.empty((len(poses), SIZE, SIZE), np.float16)
    for s in range(0, len(poses), batch):
        c2w = torch.as_tensor(poses[s : s + batch], dtype=torch.float32, device=device)
        with torch.no_grad():
            crops = render_rgbd_crops(scene, c2w, (fx, fx), gel, framing)
        d = crops.depth.astype(np.float32)
        if reference == "gel":
            shift = (depths[s : s + batch] / framing.depth_window)[:, None, None]
            d = np.where(d < 1.0, np.clip(d - shift, 0.0, 1.0), d)
        rgb[s : s + len(c2w)], depth[s : s + len(c2w)] = crops.rgb, d.astype(np.float16)
    return PressRGBD(rgb, depth, poses, crop_pixels(sensor, framing, sp.centers))


def model_dataset(checkpoint: str | Path) -> Path | None:
    """The paired dataset a checkpoint's run was trained on (the first of its manifest's ``datasets``, under
    the run's ``<data_root>/pairs/`` or as a path); None where the run records none or it is gone."""
    ckpt = Path(checkpoint)
    run = ckpt.parent
    manifest = run / MANIFEST
    if not manifest.is_file():
        return None
    datasets = read_json(manifest, "model manifest").get("datasets") or []
    if not datasets:
        return None
    name = Path(str(datasets[0])).expanduser()
    for folder in (name, run.parent.parent / "pairs" / str(datasets[0])):
        if (folder / MANIFEST).is_file():
            return folder
    return None


def dataset_framing(folder: str | Path | None) -> Framing:
    """The crop and depth settings a paired dataset was made with (its manifest's ``preprocess``), or
    ``Framing()``'s defaults for None or a dataset that records none."""
    if folder is None:
        return Framing()
    pre = read_json(Path(folder) / MANIFEST, "dataset manifest").get("preprocess") or {}
    return Framing.from_settings({k: v for k, v in pre.items() if k != "crop_px"}) if pre else Framing()


def checkpoint_framing(checkpoint: str | Path) -> Framing:
    """The crop and depth settings of the data a checkpoint was trained on (``model_dataset``), or
    ``Framing()``'s defaults where the dataset is not found."""
    return dataset_framing(model_dataset(checkpoint))


def to_sensor_size(images: np.ndarray, width: int, height: int) -> np.ndarray:
    """``[N, S, S, 3]`` uint8 generated images resized to ``width x height`` (bilinear, antialiased as the
    pairing stage's resize of tactile images to 128 px)."""
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float()
    y = F.interpolate(t, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
    return y.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()


def load_press_generator(checkpoint: str | Path, device: str = "cpu") -> Any:
    """A trained generator (``load_generator``) that takes RGB-D and a background only; a one-line TnfError
    for a missing checkpoint or a generator that needs more (a prior, surface points, a force)."""
    from tnf.generators import load_generator

    ckpt = Path(checkpoint)
    if not ckpt.is_file():
        raise TnfError(f"checkpoint not found: {ckpt}")
    system = load_generator(ckpt, device)
    hp = system.hparams["generator"]
    extra = [i for i in (hp.get("inputs") or ()) if i in PRESS_LESS_INPUTS]
    if extra or hp.get("force", "none") != "none":
        what = ", ".join(extra) if extra else f"force={hp.get('force')}"
        raise TnfError(f"{ckpt}: the generator takes {what}; presses give RGB-D and a background only")
    size = int(hp.get("image_size", SIZE))
    if size != SIZE:
        raise TnfError(f"{ckpt} generates {size} px images; tnf datasets use {SIZE} px")
    return system


def generate_presses(
    checkpoint: str | Path,
    sensor: Sensor,
    sp: SensorPresses,
    radius_m: float,
    depth_scale: float = 1.0,
    *,
    framing: Framing | None = None,
    reference: str = "gel",
    mirror: bool = False,
    seed: int = 0,
    device: str = "cpu",
    batch: int = 32,
) -> np.ndarray:
    """A trained generator's tactile images of the presses, ``[N, H, W, 3]`` uint8 at the sensor's size.

    The generator (``checkpoint``, loaded as ``tnf generate`` loads it) gets each press's RGB-D
    (``press_rgbd``, framed as its training data unless ``framing`` is given) and the presses' real
    background (``sp.background``: the calibrated sensor's background is that frame), both at 128 px; its
    images are resized to the sensor's ``width x height``. ``mirror`` averages each image with that of the
    mirrored press where the sensor has a mirror symmetry (``generate.mirror_average``). ``seed`` seeds the
    generator's dropout noise.
    """
    import torch

    from tnf.generators.generate import condition_batch, tactile_images

    system = load_press_generator(checkpoint, device)
    views = press_rgbd(
        sensor, sp, radius_m, depth_scale, framing=framing or checkpoint_framing(checkpoint),
        reference=reference, device=device, batch=batch,
    )  # fmt: skip
    channels = sensor.mirror_channels() if mirror else None
    background = resize_uint8(sp.background, SIZE)
    torch.manual_seed(seed)
    out = []
    with torch.no_grad():
        for s in range(0, len(views.rgb), batch):
            cond = condition_batch(views.rgb[s : s + batch], views.depth[s : s + batch], background, device)
            out.append(tactile_images(system, cond, channels))
    images = np.concatenate(out) if out else np.empty((0, SIZE, SIZE, 3), np.uint8)
    return to_sensor_size(images, sensor.width, sensor.height)


def press_indices(value: Any, where: str) -> list[int]:
    """A list of press numbers from a config value; a one-line TnfError otherwise."""
    if not isinstance(value, Sequence) or isinstance(value, str):
        raise TnfError(f"{where} must be a list of press numbers, got {value!r}")
    out = list(value)
    if not all(isinstance(i, int) and not isinstance(i, bool) for i in out):
        raise TnfError(f"{where} must be a list of press numbers, got {out!r}")
    return out
