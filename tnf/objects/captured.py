"""``captured``: your own objects, as camera images with poses and real tactile frames (no meshes).

Layout of ``objects.root``, one folder per object (the folder's name is the object's name)::

    <root>/<object>/
        transforms.json         camera views, instant-ngp / nerfstudio format: fl_x, fl_y (or camera_angle_x),
                                cx, cy, w, h, frames: [{"file_path": "images/0001.png",
                                "transform_matrix": 4x4 camera-to-world}, ...]
        transforms_test.json    optional held-out views, same format; without it, frames 0, k, 2k, ... of
                                transforms.json are held out (k = objects.test_every)
        images/...              the images the frames name: RGB (PNG, JPEG) or RGBA whose alpha masks the object
        depth/...               optional, per frame ``depth_file_path``: float32 .npy z-depth in metres, 0 = empty
        tactile/
            touches.json        [{"image": "frames/0001.png", "c2w": 4x4, "split": "train"}, ...]
            background.png      the tactile sensor's image with nothing touching it
            frames/...          the tactile images, sensor.width x sensor.height pixels

Conventions: every pose is a camera-to-world 4x4 matrix in metres, OpenGL convention (the camera looks along
its -z axis, +y up), and one object's cameras and tactile sensor share one frame. A touch's ``c2w`` is the pose
of the tactile sensor while it presses the object, in tnf's sensor frame: the origin is the sensor's internal
camera, the gel lies in front of it along -z (its rim ``sensor.camera_distance`` away). Its ``split`` is
``train`` (the default), ``val`` (model selection) or ``novel_view`` (the novel-view test set). Frames of one
press may share a pose.

``tnf capture objects=captured objects.root=DIR`` imports the views into ``<data_root>/capture/captured/<object>/``
in the layout that rendered captures have (validated, images as PNG, the world origin moved to the point the
cameras look at when ``objects.centre`` is set). ``tnf touch`` then imports the tactile frames into
``<data_root>/touch/<sensor>/captured/<object>/`` in the same frame, each touch starting where the sensor's axis
leaves the sphere of ``touch.radius`` around the object (where simulated touches start and ``tnf generate``
samples). Every later stage runs unchanged. What needs a mesh (``tnf objects``, ``pair.scene_source=mesh``,
touch simulation) stops with an error.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tnf.artifacts import files_digest, read_json, write_json
from tnf.cameras import Views, read_views
from tnf.errors import TnfError
from tnf.objects import TOUCH_SPLITS, ObjectSource
from tnf.registry import FROM_YAML, config_to_dict, yaml_defaults
from tnf.touches import TouchRecord, as_matrix, as_point

if TYPE_CHECKING:  # pragma: no cover
    from tnf.artifacts import ArtifactStore

log = logging.getLogger(__name__)

TOUCH_KEYS = ("image", "c2w", "split")
"""Keys of one entry of ``touches.json`` (``split`` is optional)."""


class Captured(ObjectSource):
    """Your own objects: camera images with poses (transforms.json) and real tactile frames; no meshes."""

    @dataclass
    @yaml_defaults("objects/captured")
    class Config:
        root: str = FROM_YAML
        """The folder with one sub-folder per object, ``<root>/<object>/transforms.json`` (required)."""
        test_every: int = FROM_YAML
        """Without transforms_test.json, frames 0, k, 2k, ... of transforms.json are held out as test views; 0: none."""
        centre: bool = FROM_YAML
        """Move the world origin to the point the cameras look at (nearest to their view axes); false: the poses'
        origin must be the object's centre."""

        def validate(self) -> None:
            if self.root in ("", "???"):
                raise ValueError("root is required: the folder of your objects (objects.root=/data/my_objects)")
            if self.test_every < 0 or self.test_every == 1:
                raise ValueError(f"test_every must be 0 (no test views) or >= 2, got {self.test_every}")

    name = "captured"

    def __init__(self, cfg: Config):
        self.cfg = cfg
        self.root = Path(cfg.root).expanduser()
        if not self.root.is_dir():
            raise TnfError(f"objects.root: folder not found: {self.root}")
        self._names = sorted(p.name for p in self.root.iterdir() if p.is_dir() and not p.name.startswith("."))
        if not self._names:
            raise TnfError(f"objects.root: no object folders (<object>/transforms.json) in {self.root}")

    def names(self) -> list[str]:
        return list(self._names)

    def where(self, name: str) -> str:
        return str(self.root / name)

    def load(self, name: str) -> Any:
        self.check_name(name)
        raise TnfError(
            f"object source {self.name!r} has camera images, not meshes: object {name!r} ({self.where(name)}) "
            "cannot be loaded as a mesh (tnf objects, touch simulation and pair.scene_source=mesh need one)"
        )

    def views(self, name: str) -> Path:
        self.check_name(name)
        return self.root / name / "transforms.json"

    def touches(self, name: str) -> Path:
        self.check_name(name)
        path = self.root / name / "tactile" / "touches.json"
        if not path.is_file():
            raise TnfError(
                f"tactile frames not found: {path} (object {name!r} of source {self.name!r}, which has no mesh "
                "to simulate touches from)"
            )
        return path

    def describe(self) -> dict[str, Any]:
        """``{"name", **config}`` as plain JSON data (part of the imported items' configs)."""
        return {"name": self.name, **config_to_dict(self.cfg)}


# -- camera views ------------------------------------------------------------------------------------------
def view_centre(c2w: np.ndarray, where: str = "poses") -> np.ndarray:
    """The point [3] (metres) nearest to every camera's view axis in the least-squares sense; ``c2w`` [N, 4, 4].

    Cameras around an object look at it, so this is the object's centre (up to how well they were aimed).
    """
    o = c2w[:, :3, 3]
    d = -c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    # Distance of p from the axis (o, d) is |(I - d d^T)(p - o)|; the normal equations sum those projectors.
    proj = np.eye(3) - d[:, :, None] * d[:, None, :]
    a = proj.sum(0)
    b = (proj @ o[:, :, None]).sum(0)[:, 0]
    if np.linalg.cond(a) > 1e6:
        raise TnfError(
            f"{where}: the cameras' view axes are (nearly) parallel, so the point they look at is undefined; "
            "set objects.centre=false and give poses with the object's centre at the origin"
        )
    return np.linalg.solve(a, b)


def _transforms(views: Views, split: str, shift: np.ndarray) -> dict[str, Any]:
    """``transforms.json`` content of ``views`` with their translations moved by ``shift`` (metres)."""
    fx, fy, cx, cy = views.intrinsics
    frames = []
    for i, m in enumerate(views.c2w):
        m = m.copy()
        m[:3, 3] += shift
        frame: dict[str, Any] = {"file_path": f"images/{split}_{i:03d}.png", "transform_matrix": m.tolist()}
        if views.depth is not None:
            frame["depth_file_path"] = f"depth/{split}_{i:03d}.npy"
        frame["source_frame"] = int(views.frames[i])  # the frame's index in the imported file
        frames.append(frame)
    meta: dict[str, Any] = {
        "camera_model": "OPENCV",
        "fl_x": fx,
        "fl_y": fy,
        "cx": cx,
        "cy": cy,
        "w": views.width,
        "h": views.height,
        "camera_angle_x": 2 * math.atan(views.width / 2 / fx),
        "camera_angle_y": 2 * math.atan(views.height / 2 / fy),
        "frames": frames,
    }
    if views.depth is not None:
        meta["depth_unit_scale_factor"] = 1.0  # depth files are in metres
    return meta


def _write_views(folder: Path, split: str, views: Views, shift: np.ndarray) -> None:
    from PIL import Image

    meta = _transforms(views, split, shift)
    (folder / "images").mkdir(exist_ok=True)
    if views.depth is not None:
        (folder / "depth").mkdir(exist_ok=True)
    for k, frame in enumerate(meta["frames"]):
        Image.fromarray(views.images[k], "RGBA").save(folder / frame["file_path"], compress_level=1)
        if views.depth is not None:
            np.save(folder / frame["depth_file_path"], views.depth[k].astype(np.float32))
    write_json(folder / ("transforms.json" if split == "train" else f"transforms_{split}.json"), meta)


def _warn_distortion(path: Path) -> None:
    """Say so when the transforms file gives lens distortion: tnf's cameras are pinholes."""
    import json

    meta = json.loads(path.read_text())
    coeffs = {k: meta[k] for k in ("k1", "k2", "k3", "k4", "p1", "p2") if isinstance(meta.get(k), (int, float))}
    if any(v != 0 for v in coeffs.values()):
        log.warning("%s: lens distortion %s is ignored (pinhole cameras); undistort the images first", path, coeffs)


def import_views(store: ArtifactStore, source: ObjectSource, name: str) -> dict[str, Any]:
    """Import object ``name``'s camera views into ``capture/<source>/<name>/``, as ``tnf capture`` writes them.

    Reads (and validates, with one-line errors naming the file) ``transforms.json`` and, when present,
    ``transforms_test.json``; else holds out every ``test_every``-th frame. Writes RGBA PNGs, depth .npy files
    when every frame has depth, and the transforms files with the world origin at the point the cameras look
    at (``centre``; the shift, metres, is the manifest's ``world_offset_m``). Skipped when already imported
    from the same files and settings. Returns the row ``tnf capture`` prints: object, status, views, seconds.
    """
    if not isinstance(source, Captured):
        raise TnfError(f"object source {source.name!r} gives camera views but is not a 'captured' source")
    t0 = time.perf_counter()
    file = source.views(name)
    config = {"objects": source.describe(), "files": files_digest(file.parent, skip="tactile")}
    if store.is_done("capture", source.name, name, config=config):
        return {"object": name, "status": "skipped (done)", "views": None, "seconds": 0.0}
    views = read_views(file)
    _warn_distortion(file)
    test_file = file.with_name("transforms_test.json")
    if test_file.is_file():
        train, test = views, read_views(test_file)
    elif source.cfg.test_every:
        held = views.frames % source.cfg.test_every == 0
        if held.all():
            raise TnfError(
                f"{file}: {len(views.frames)} frame(s), none left for training after holding out every "
                f"{source.cfg.test_every}th; add frames, or set objects.test_every=0"
            )
        train, test = views.take(~held), views.take(held)
    else:
        train, test = views, None
    shift = -view_centre(views.c2w, str(file)) if source.cfg.centre else np.zeros(3)
    info = {
        "object": name,
        "source": source.name,
        "num_views": len(train.frames),
        "num_test_views": len(test.frames) if test is not None else 0,
        "imported_from": str(file),
        "world_offset_m": shift.tolist(),
        "depth": train.depth is not None,
    }
    with store.writing("capture", source.name, name, config=config, info=info) as tmp:
        _write_views(tmp, "train", train, shift)
        if test is not None:
            _write_views(tmp, "test", test, shift)
    n = info["num_views"] + info["num_test_views"]
    return {"object": name, "status": "imported", "views": n, "seconds": time.perf_counter() - t0}


# -- tactile frames ----------------------------------------------------------------------------------------
@dataclass
class RealTouch:
    """One entry of ``touches.json``."""

    image: Path  # the tactile image file
    c2w: np.ndarray  # [4, 4] sensor pose while pressing, camera-to-world, metres, in the user's frame
    split: str  # train, val or novel_view


def read_touches(path: Path) -> list[RealTouch]:
    """The entries of a ``touches.json``, validated: one-line TnfErrors name the file and the entry."""
    data = read_json(path, "touches file")
    if not isinstance(data, list) or not data:
        raise TnfError(f"{path}: expected a non-empty list of touches ({{'image', 'c2w', 'split'}}), got {data!r:.60}")
    out = []
    for i, t in enumerate(data):
        if not isinstance(t, dict):
            raise TnfError(f"{path}: touch {i} must be an object with keys image, c2w (and split), got {t!r:.60}")
        unknown = sorted(set(t) - set(TOUCH_KEYS))
        if unknown:
            raise TnfError(f"{path}: touch {i} has unknown key {unknown[0]!r}; keys: {', '.join(TOUCH_KEYS)}")
        for key in ("image", "c2w"):
            if key not in t:
                raise TnfError(f"{path}: touch {i} is missing key {key!r}")
        if not isinstance(t["image"], str) or not t["image"]:
            raise TnfError(f"{path}: touch {i} image must be a file path, got {t['image']!r}")
        split = t.get("split", "train")
        if split not in TOUCH_SPLITS:
            raise TnfError(f"{path}: touch {i} split must be one of {', '.join(TOUCH_SPLITS)}, got {split!r}")
        image = path.parent / t["image"]
        if not image.is_file():
            raise TnfError(f"{path}: touch {i} image not found: {image}")
        out.append(RealTouch(image, _rigid_pose(t["c2w"], f"{path}: touch {i} c2w"), split))
    return out


def _rigid_pose(value: Any, where: str) -> np.ndarray:
    """``value`` as a [4, 4] float64 rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)."""
    try:
        m = np.asarray(value, dtype=np.float64)
    except (ValueError, TypeError):
        raise TnfError(f"{where} is not a 4x4 matrix of numbers") from None
    if m.shape != (4, 4):
        raise TnfError(f"{where} has shape {list(m.shape)}, expected [4, 4]")
    if not np.isfinite(m).all():
        raise TnfError(f"{where} holds NaN or infinite values")
    r = m[:3, :3]
    if not np.allclose(m[3], (0, 0, 0, 1), atol=1e-6) or not np.allclose(r.T @ r, np.eye(3), atol=1e-3):
        raise TnfError(f"{where} is not a rigid transform (rotation with orthonormal columns, last row 0 0 0 1)")
    if np.linalg.det(r) < 0:
        raise TnfError(f"{where} is a reflection (determinant -1), not a rotation")
    return m


def _check_size(path: Path, sensor: Any, what: str) -> None:
    """An RGB(A) image of the sensor's size, else a TnfError naming the file, its size and the expected one."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            size, mode = im.size, im.mode
    except (UnidentifiedImageError, OSError) as e:
        raise TnfError(f"{path}: not a readable image ({e})") from None
    if mode not in ("RGB", "RGBA"):
        raise TnfError(f"{path}: {what} must be an RGB image, got mode {mode}")
    if size != (sensor.width, sensor.height):
        raise TnfError(
            f"{path}: {what} is {size[0]}x{size[1]} pixels, expected {sensor.width}x{sensor.height} "
            f"(sensor.width x sensor.height of sensor {sensor.name!r})"
        )


def start_pose(c2w: np.ndarray, radius: float) -> np.ndarray | None:
    """``c2w`` [4, 4] moved back along its +z axis to the sphere of ``radius`` metres around the origin;
    None when ``c2w`` is not inside that sphere."""
    p, back = c2w[:3, 3], c2w[:3, 2] / np.linalg.norm(c2w[:3, 2])
    pb, c = float(p @ back), float(p @ p) - radius**2
    if c >= 0:
        return None
    out = c2w.copy()
    out[:3, 3] = p + (-pb + math.sqrt(pb * pb - c)) * back
    return out


def import_touches(store: ArtifactStore, sensor: Any, source: ObjectSource, name: str, start_radius: float) -> str:
    """Import object ``name``'s real tactile frames into ``touch/<sensor>/<source>/<name>/`` as ``tnf touch``
    writes simulated ones; returns a one-line summary.

    Every touch keeps its entry's position in ``touches.json`` as its index. Its ``contact_c2w`` is the given
    pose moved into the imported capture's frame (``world_offset_m``), ``start_c2w`` the same pose moved back
    along the sensor's axis onto the sphere of ``start_radius`` metres around the object (the camera that
    ``tnf pair`` renders from), ``contact_point`` the centre of the gel's surface at contact; force and
    penetration are null (not measured). Images must have the sensor's size (no resizing). Needs the object's
    imported capture (``tnf capture``). Skipped when already imported from the same files and settings.
    """
    if not isinstance(source, Captured):
        raise TnfError(f"object source {source.name!r} gives tactile frames but is not a 'captured' source")
    path = source.touches(name)
    tactile = path.parent
    store.require("capture", source.name, name, hint=f"run `tnf capture object={name}` first: it sets the frame")
    capture = store.manifest("capture", source.name, name) or {}
    item = (sensor.name, source.name, name)
    config = {
        "sensor": sensor.describe(),
        "objects": source.describe(),
        "capture": capture.get("config_hash"),
        "start_radius": float(start_radius),
        "files": files_digest(tactile),
    }
    if store.is_done("touch", *item, config=config):
        return f"touch {'/'.join(item)}: done, skipped"
    touches = read_touches(path)
    background = tactile / "background.png"
    if not background.is_file():
        raise TnfError(f"sensor background not found: {background} (the sensor's image with nothing touching it)")
    _check_size(background, sensor, "the background")
    for t in touches:
        _check_size(t.image, sensor, "tactile image")
    records = _touch_records(touches, capture, sensor, start_radius, path)
    counts = {s: sum(r.split == s for r in records) for s in TOUCH_SPLITS}
    info = {
        "sensor": sensor.describe(),
        "object": name,
        "source": source.name,
        "touches": [r.to_json() for r in records],
        "counts": {**counts, "discarded": dict.fromkeys(TOUCH_SPLITS, 0)},
        "width": sensor.width,
        "height": sensor.height,
        "intrinsics": list(sensor.intrinsics()),
        "imported_from": str(path),
        "start_radius": float(start_radius),
    }
    with store.writing("touch", *item, config=config, info=info) as tmp:
        _copy_images(tmp, background, [t.image for t in touches], [r.image for r in records])
    return f"touch {'/'.join(item)}: {len(records)} touches imported from {path}"


def _touch_records(
    touches: Sequence[RealTouch], capture: dict[str, Any], sensor: Any, start_radius: float, path: Path
) -> list[TouchRecord]:
    """The record of each imported touch of ``touches.json`` (``path``), as ``import_touches`` describes
    it: poses [4, 4] camera-to-world in the capture's frame (metres; ``capture``: its manifest), the contact point
    (metres) in front of the sensor's gel, force and penetration null."""
    shift = np.asarray(capture.get("world_offset_m", [0.0, 0.0, 0.0]), dtype=np.float64)
    # The gel's surface centre: the rim plane plus the undeformed gel's bulge, in front of the sensor's camera.
    gel_front = float(sensor.cfg.camera_distance) + float(np.max(sensor.gel_surface()))
    records: list[TouchRecord] = []
    for i, t in enumerate(touches):
        contact = t.c2w.copy()
        contact[:3, 3] += shift
        start = start_pose(contact, start_radius)
        if start is None:
            dist = float(np.linalg.norm(contact[:3, 3]))
            raise TnfError(
                f"{path}: touch {i}: the sensor is {dist:.3f} m from the object's centre, not inside touch.radius="
                f"{start_radius:g} m where touches start; are the poses in metres and in the cameras' frame?"
            )
        axis = -contact[:3, 2] / np.linalg.norm(contact[:3, 2])
        records.append(
            TouchRecord(
                index=i,
                split=t.split,
                image=f"images/{i:05d}.png",
                start_c2w=as_matrix(start),
                contact_c2w=as_matrix(contact),
                contact_point=as_point(contact[:3, 3] + gel_front * axis),
                force=None,
                penetration=None,
            )
        )
    return records


def _copy_images(folder: Path, background: Path, images: Sequence[Path], names: Sequence[str]) -> None:
    """Write ``background`` and each of ``images`` (as ``names``, relative to ``folder``) into ``folder`` as RGB
    PNG files; a TnfError names an image that cannot be read."""
    from PIL import Image

    (folder / "images").mkdir()
    with Image.open(background) as im:
        im.convert("RGB").save(folder / "background.png")
    for image, name in zip(images, names):
        try:
            with Image.open(image) as im:
                im.convert("RGB").save(folder / name, compress_level=1)
        except OSError as e:  # truncated or corrupt past the header
            raise TnfError(f"{image}: not a readable image ({e})") from None
