"""The ``Sensor`` base class: the public API for tactile sensors, in-tree and from plugins.

A vision-based tactile sensor (Digit, OmniTact, GelSight...) is a camera looking through a soft elastomer
gel lit by coloured lights from the inside. In tnf a sensor is mostly *data* (its ``Config``): image size,
field of view, gel geometry, elastomer stiffness, lights, noise and blur, plus a few methods the simulator
calls. A new sensor usually only changes the data; it may override one or two hooks:

* ``gel_surface()`` - the shape of the undeformed gel (default: a separable parabolic sag),
* ``background(seed)`` - the image the sensor shows with nothing touching it,
* ``decorate(image, indentation)`` - draw things onto the finished tactile image (e.g. printed markers
  that move with the gel),
* ``shade(points, normals)`` - the lighting model (the warp simulator's fast path implements the default
  model on the device; a sensor that overrides ``shade`` is rendered by calling it on the host instead).

Frames and units: the **sensor frame** is the camera frame in the OpenGL convention: camera at the origin,
looking along its -z axis, +x right, +y up, metres. The gel lies in front of the camera (negative z). A
sensor pose is a camera-to-world 4x4 matrix. Images are ``[H, W, 3]`` uint8, row 0 at the top (+y).

A plugin sensor, e.g. in a package ``tnf_gelsight`` registered through the ``tnf.sensors`` entry point, takes
every value from its YAML (``tnf_gelsight/conf/sensor/gelsight.yaml``: all of ``SensorConfig``'s fields and its
own)::

    from dataclasses import dataclass
    from pathlib import Path
    from tnf.registry import FROM_YAML, yaml_defaults
    from tnf.sensors import Sensor, SensorConfig

    class GelSight(Sensor):
        \"\"\"GelSight Mini with a marker grid.\"\"\"

        @dataclass
        @yaml_defaults("sensor/gelsight", conf=Path(__file__).parent / "conf")
        class Config(SensorConfig):
            marker_spacing: float = FROM_YAML
            \"\"\"Distance between printed markers, metres.\"\"\"

        def decorate(self, image, indentation):
            ...  # draw dark dots at the marker positions, shifted with the gel
            return image
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tnf.errors import TnfError
from tnf.registry import FROM_YAML, config_to_dict
from tnf.sensors.calibration import Calibration, load_calibration


@dataclass
class Light:
    """A point light inside the sensor."""

    position: tuple[float, float, float] = (0.0, 0.0, -0.02)
    """Position in the sensor frame (camera at origin, looking along -z), metres."""
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Linear RGB colour, each channel in [0, 1]."""
    intensity: float = 1.0
    """Brightness multiplier (dimensionless)."""

    def validate(self) -> None:
        if any(c < 0 for c in self.color):
            raise ValueError(f"light color channels must be >= 0, got {self.color}")
        if self.intensity < 0:
            raise ValueError(f"light intensity must be >= 0, got {self.intensity}")


@dataclass
class SensorConfig:
    """Data shared by every sensor. A sensor's ``Config`` subclasses it, takes every value from the sensor's YAML
    (``@yaml_defaults("sensor/NAME")``) and may add fields (document each)."""

    width: int = FROM_YAML
    """Image width W, pixels."""
    height: int = FROM_YAML
    """Image height H, pixels."""
    fov: float = FROM_YAML
    """Vertical field of view of the camera, degrees (square pixels; principal point at the centre)."""
    camera_distance: float = FROM_YAML
    """Distance from the camera to the plane of the gel's rim along the view axis, metres."""
    gel_width: float = FROM_YAML
    """Gel size along the image x axis, metres."""
    gel_height: float = FROM_YAML
    """Gel size along the image y axis, metres."""
    sag: float = FROM_YAML
    """How far the gel's centre bulges out beyond its rim (convex curvature), metres; 0 = flat."""
    thickness: float = FROM_YAML
    """Elastomer thickness over its rigid backing, metres (a thin layer is stiffer than a half-space)."""
    young_modulus: float = FROM_YAML
    """Elastomer Young's modulus E, pascals."""
    poisson_ratio: float = FROM_YAML
    """Elastomer Poisson ratio (nearly incompressible silicone: ~0.5)."""
    max_penetration: float = FROM_YAML
    """Deepest indentation the simulator considers, metres (presses stop there)."""
    force_range: tuple[float, float] = FROM_YAML
    """Normal forces the sensor is used with, newtons (a target force outside it is an error)."""
    lights: list[Light] = FROM_YAML
    """Point lights inside the sensor."""
    ambient: float = FROM_YAML
    """Ambient light level added to the shading, in [0, 1]."""
    diffuse: float = FROM_YAML
    """Weight of Lambertian (diffuse) shading."""
    specular: float = FROM_YAML
    """Weight of Blinn-Phong specular highlights."""
    shininess: float = FROM_YAML
    """Blinn-Phong exponent (higher = tighter highlights)."""
    contrast: float = FROM_YAML
    """Gain from shading difference (deformed minus undeformed, in [0, 1] units) to 8-bit image values."""
    blur_sigma: float = FROM_YAML
    """Gaussian blur of the difference image, pixels (the gel and lens are not perfectly sharp); 0 = off."""
    noise_std: float = FROM_YAML
    """Standard deviation of Gaussian pixel noise, 8-bit units; 0 = off."""
    background_image: str | None = FROM_YAML
    """Image file of the sensor with nothing touching it (a real photo); null = procedural background."""
    background_seed: int = FROM_YAML
    """Seed of the procedural background (gel texture, LED variation)."""
    calibration: str | None = FROM_YAML
    """Folder written by ``tnf calibrate`` (measured shading table, blur, noise, gel fall-off and background);
    null = the hand-set optics above. When set, its values replace ``lights``, ``contrast``, ``blur_sigma``,
    ``noise_std``, the background and the simulator's ``falloff``."""

    def validate(self) -> None:
        if self.width < 8 or self.height < 8:
            raise ValueError(f"image size must be at least 8x8 pixels, got {self.width}x{self.height}")
        if not 1.0 <= self.fov <= 170.0:
            raise ValueError(f"fov must be in [1, 170] degrees, got {self.fov}")
        for name in ("camera_distance", "gel_width", "gel_height", "thickness", "young_modulus", "max_penetration"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.sag < 0:
            raise ValueError(f"sag must be >= 0, got {self.sag}")
        if not 0.0 <= self.poisson_ratio < 0.5:
            raise ValueError(f"poisson_ratio must be in [0, 0.5), got {self.poisson_ratio}")
        lo, hi = self.force_range
        if not 0 <= lo < hi:
            raise ValueError(f"force_range must be (min, max) with 0 <= min < max, got {self.force_range}")
        if not self.lights:
            raise ValueError("a sensor needs at least one light")
        if self.blur_sigma < 0 or self.noise_std < 0:
            raise ValueError(f"blur_sigma and noise_std must be >= 0, got {self.blur_sigma}, {self.noise_std}")


class Sensor:
    """A vision-based tactile sensor: its data (``cfg``) and the hooks the simulator calls.

    Args:
        cfg: the validated ``Config`` (build from a config node with ``SENSORS.build({"name": ..., ...})``).
    """

    Config = SensorConfig
    name: str = "sensor"
    """Registry name; set by subclasses (the registry does not set it)."""

    def __init__(self, cfg: SensorConfig):
        self.cfg = cfg
        self._calibration: Calibration | None = None

    def calibrated(self, calibration: Calibration, path: str) -> Sensor:
        """This sensor with ``calibration`` (already in memory) as its optics, recorded as coming from ``path``."""
        import dataclasses

        other = type(self)(dataclasses.replace(self.cfg, calibration=str(path)))
        other._calibration = other._checked(calibration)
        return other

    def _checked(self, cal: Calibration) -> Calibration:
        """``cal``, after checking that it was made for this sensor's image size."""
        if cal.size != (self.width, self.height):
            raise TnfError(
                f"sensor {self.name!r}: calibration {self.cfg.calibration} was made for {cal.size[0]}x{cal.size[1]}"
                f" images, the sensor's are {self.width}x{self.height} (calibrate at this size)"
            )
        return cal

    @property
    def calibration(self) -> Calibration | None:
        """The measured optics from ``cfg.calibration`` (loaded once), or None without one."""
        if self.cfg.calibration is None:
            return None
        if self._calibration is None:
            self._calibration = self._checked(load_calibration(self.cfg.calibration))
        return self._calibration

    # -- camera ---------------------------------------------------------------------------------------
    @property
    def width(self) -> int:
        return self.cfg.width

    @property
    def height(self) -> int:
        return self.cfg.height

    def intrinsics(self) -> tuple[float, float, float, float]:
        """Pinhole intrinsics ``(fx, fy, cx, cy)`` in pixels, from the vertical field of view."""
        fy = 0.5 * self.height / math.tan(math.radians(self.cfg.fov) / 2)
        return fy, fy, self.width / 2, self.height / 2

    def gel_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame ``(x, y)`` of each pixel's gel sample, each ``[H, W]`` float32 metres.

        Pixel ``(row, col)`` samples the gel where its camera ray meets the rim plane; the simulator works on
        this regular grid (the parallax across the gel's sag is neglected).
        """
        fx, fy, cx, cy = self.intrinsics()
        d = self.cfg.camera_distance
        cols = (np.arange(self.width, dtype=np.float64) + 0.5 - cx) / fx * d
        rows = -(np.arange(self.height, dtype=np.float64) + 0.5 - cy) / fy * d
        x, y = np.meshgrid(cols, rows)
        return x.astype(np.float32), y.astype(np.float32)

    def view_size(self) -> tuple[float, float]:
        """``(width, height)`` in metres of the gel patch the tactile image shows: ``gel_grid``'s extent, pixel
        edge to pixel edge. An RGB-D crop of this size around the sensor's axis is pixel-aligned with the image
        (``pair.crop_extent=sensor``)."""
        dx, dy = self.pixel_size()
        return self.width * dx, self.height * dy

    def pixel_size(self) -> tuple[float, float]:
        """Gel area one pixel covers, ``(dx, dy)`` metres."""
        fx, fy, _, _ = self.intrinsics()
        return self.cfg.camera_distance / fx, self.cfg.camera_distance / fy

    def gel_mask(self) -> np.ndarray:
        """``[H, W]`` bool: pixels that see gel (the image may extend beyond the gel's edge)."""
        x, y = self.gel_grid()
        return (np.abs(x) <= self.cfg.gel_width / 2) & (np.abs(y) <= self.cfg.gel_height / 2)

    def gel_surface(self) -> np.ndarray:
        """Undeformed gel heights ``[H, W]`` float32 metres: how far the surface bulges out beyond the rim plane
        (toward the object, along -z). Default: a separable parabola, ``sag`` at the centre, 0 at the edges.

        The surface point of pixel ``(r, c)`` is ``(x, y, -(camera_distance + h))`` with ``x, y = gel_grid()``.
        """
        x, y = self.gel_grid()
        u = 1.0 - (2.0 * x / self.cfg.gel_width) ** 2
        v = 1.0 - (2.0 * y / self.cfg.gel_height) ** 2
        return (self.cfg.sag * np.clip(u, 0, None) * np.clip(v, 0, None)).astype(np.float32)

    def gel_points(self, heights: np.ndarray | None = None) -> np.ndarray:
        """Sensor-frame points ``[H, W, 3]`` of the gel surface for outward heights ``[H, W]`` (default: undeformed)."""
        x, y = self.gel_grid()
        h = self.gel_surface() if heights is None else heights
        return np.stack([x, y, -(self.cfg.camera_distance + h)], axis=-1).astype(np.float32)

    # -- elastomer ------------------------------------------------------------------------------------
    @property
    def effective_modulus(self) -> float:
        """Contact modulus ``E* = E / (1 - nu^2)`` against a rigid indenter, pascals."""
        return self.cfg.young_modulus / (1.0 - self.cfg.poisson_ratio**2)

    def check_force(self, force: float, what: str | None = None) -> None:
        """Raise a TnfError when ``force`` (newtons) is outside the sensor's force range; ``what`` names the
        setting the force came from (the message then starts with it)."""
        lo, hi = self.cfg.force_range
        if not lo < force <= hi:
            where = f"{what}: " if what else ""
            raise TnfError(
                f"{where}sensor {self.name!r}: force must be in ({lo}, {hi}] N, got {force} (sensor.force_range)"
            )

    # -- lighting -------------------------------------------------------------------------------------
    def light_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """``(positions [L, 3] metres in the sensor frame, radiance [L, 3] = color * intensity)``, float32."""
        pos = np.array([lt.position for lt in self.cfg.lights], dtype=np.float32).reshape(-1, 3)
        rad = np.array([np.asarray(lt.color) * lt.intensity for lt in self.cfg.lights], dtype=np.float32)
        return pos, rad.reshape(-1, 3)

    def shade(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Light the gel: ``points`` and unit ``normals`` ``[..., 3]`` (sensor frame, normals facing the camera)
        -> radiance ``[..., 3]`` float32, roughly in [0, 1].

        Default: ambient + Lambertian + Blinn-Phong per light, viewed from the camera at the origin. The warp
        simulator evaluates this same model on the device; override it for another lighting model (the
        simulator then calls it on the host).
        """
        c = self.cfg
        pos, rad = self.light_arrays()
        view = -points / np.linalg.norm(points, axis=-1, keepdims=True)
        out = np.full(points.shape[:-1] + (3,), c.ambient, dtype=np.float32)
        for p, r in zip(pos, rad):
            to_light = p - points
            ldir = to_light / np.linalg.norm(to_light, axis=-1, keepdims=True)
            ndl = np.clip((normals * ldir).sum(-1, keepdims=True), 0, None)
            half = ldir + view
            half /= np.linalg.norm(half, axis=-1, keepdims=True)
            ndh = np.clip((normals * half).sum(-1, keepdims=True), 0, None)
            out += r * (c.diffuse * ndl + c.specular * ndh**c.shininess)
        return out.astype(np.float32)

    def mirror_channels(self) -> tuple[int, ...] | None:
        """The sensor's left-right mirror symmetry, if it has one, else None.

        Returns the colour-channel order ``p`` for which pressing the mirror image of a surface (``x -> -x`` in
        the sensor frame) gives this sensor's image of the original, flipped left-right, with channels
        ``p``: ``image[:, ::-1][..., p]``. Pairs mirrored this way are as real as the simulated ones, which makes
        the mirror a free augmentation (``data.augment=[mirror]``). The Digit has one, ``(1, 0, 2)``: its red and
        green LEDs sit mirror-wise at 30 and 150 degrees, its blue one on the axis.

        Checked numerically on what this sensor computes: its pixel grid, ``gel_mask``, ``gel_surface`` and
        ``shade`` (at random points and normals), so a sensor that overrides them is judged by its own code. A
        sensor that ``decorates`` its images (markers), or has a calibration, is taken to have none.
        """
        if self.decorates or self.cfg.calibration is not None:
            return None  # a measured shading table need not be mirror symmetric
        x, _ = self.gel_grid()
        h = self.gel_surface()
        mask = self.gel_mask()
        if not (
            np.allclose(x, -x[:, ::-1], atol=1e-9)
            and np.array_equal(mask, mask[:, ::-1])
            and np.allclose(h, h[:, ::-1], atol=1e-9)
        ):
            return None
        rng = np.random.default_rng(0)
        points = self.gel_points(h)[mask]
        points = points[rng.choice(len(points), size=min(512, len(points)), replace=False)]
        normals = rng.normal(size=points.shape) * 0.5 + np.array([0.0, 0.0, 1.0])
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        flip = np.array([-1.0, 1.0, 1.0], dtype=np.float32)
        direct = self.shade(points, normals.astype(np.float32)).astype(np.float64)
        mirrored = self.shade(points * flip, (normals * flip).astype(np.float32)).astype(np.float64)
        tol = 1e-4 * max(float(np.abs(direct).max()), 1e-6)
        for p in itertools.permutations(range(direct.shape[-1])):
            if np.allclose(mirrored, direct[..., list(p)], atol=tol, rtol=0):
                return tuple(p)
        return None

    def surface_normals(self, heights: np.ndarray) -> np.ndarray:
        """Unit normals ``[H, W, 3]`` facing the camera (+z) of the surface with outward heights ``[H, W]``."""
        dx, dy = self.pixel_size()
        z = -(self.cfg.camera_distance + heights.astype(np.float64))
        dzdc = np.gradient(z, axis=1) / dx  # columns grow with +x
        dzdr = np.gradient(z, axis=0) / dy  # rows grow with -y
        n = np.stack([-dzdc, dzdr, np.ones_like(z)], axis=-1)
        return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)

    def surface_slopes(self, heights: np.ndarray) -> np.ndarray:
        """Slopes ``[..., H, W, 2]`` = ``(dh/dx, dh/dy)`` (dimensionless; x right, y up) of outward heights
        ``[..., H, W]`` metres, by central differences (one-sided at the border): what a calibration's shading
        table is indexed by."""
        dx, dy = self.pixel_size()
        h = np.asarray(heights, dtype=np.float64)
        sx = np.gradient(h, axis=-1) / dx
        sy = -np.gradient(h, axis=-2) / dy  # rows grow toward -y
        return np.stack([sx, sy], axis=-1).astype(np.float32)

    # -- images ---------------------------------------------------------------------------------------
    def background(self, seed: int | None = None) -> np.ndarray:
        """The image with nothing touching the gel, ``[H, W, 3]`` uint8.

        From the calibration when there is one, else from ``background_image`` when set (resized to the sensor's
        size), else procedural: the lit undeformed gel, coloured glows near each light, vignetting and a faint gel
        texture, varied by ``seed`` (default: ``background_seed``).
        """
        if self.calibration is not None:
            return self.calibration.background.copy()
        if self.cfg.background_image:
            return load_background(self.cfg.background_image, self.width, self.height)
        return self.procedural_background(self.cfg.background_seed if seed is None else seed)

    def procedural_background(self, seed: int) -> np.ndarray:
        """Procedural background ``[H, W, 3]`` uint8 (see ``background``)."""
        rng = np.random.default_rng(seed)
        c = self.cfg
        h = self.gel_surface()
        pts = self.gel_points(h)
        lit = self.shade(pts, self.surface_normals(h))
        x, y = self.gel_grid()
        pos, rad = self.light_arrays()
        scale = max(c.gel_width, c.gel_height)
        glow = np.zeros_like(lit)
        for p, r in zip(pos, rad):
            # LEDs leave soft coloured glows near where they sit; vary their reach and strength per seed.
            reach = scale * rng.uniform(0.35, 0.6)
            d2 = (x - p[0]) ** 2 + (y - p[1]) ** 2
            glow += rng.uniform(0.35, 0.55) * r * np.exp(-d2 / (2 * reach**2))[..., None]
        base = rng.uniform(0.12, 0.2, size=3).astype(np.float32)
        img = base + 0.12 * lit / max(float(lit.max()), 1e-6) + glow
        r2 = (x / (c.gel_width / 2)) ** 2 + (y / (c.gel_height / 2)) ** 2
        img *= (1.0 - 0.35 * np.clip(r2 / 2.0, 0, 1) ** 1.5)[..., None]  # vignetting
        texture = _smooth_noise(rng, self.height, self.width, cells=12) * 0.015
        img += texture[..., None] + rng.normal(0, 0.004, size=img.shape)
        img = np.where(self.gel_mask()[..., None], img, img * 0.3)  # housing beyond the gel is dark
        return np.clip(img * 255.0, 0, 255).astype(np.uint8)

    def decorate(self, image: np.ndarray, indentation: np.ndarray) -> np.ndarray:
        """Hook to draw onto finished tactile images (e.g. markers printed on the gel).

        Args:
            image: ``[B, H, W, 3]`` uint8 tactile images.
            indentation: ``[B, H, W]`` float32 metres the gel surface moved toward the camera.
        Returns the images (may modify ``image`` in place). Default: unchanged.
        """
        return image

    @property
    def decorates(self) -> bool:
        """True when a subclass overrides ``decorate`` (the simulator then copies images to the host for it). A
        subclass whose drawing can be switched off (markers) overrides this to say whether it draws."""
        return type(self).decorate is not Sensor.decorate

    @property
    def custom_shading(self) -> bool:
        """True when a subclass overrides ``shade`` (the simulator then shades on the host)."""
        return type(self).shade is not Sensor.shade

    def describe(self) -> dict[str, Any]:
        """``{"name", "config"}`` as plain JSON data: what identifies the sensor's images (touch manifests and
        every key built from them). A calibrated sensor adds ``calibration_digest``, its calibration's content,
        and leaves the calibration folder's path out of ``config``: a data root copied to another path or machine
        keeps its touches, and a new calibration at the same path is new data."""

        out: dict[str, Any] = {"name": self.name, "config": config_to_dict(self.cfg)}
        if self.calibration is not None:
            out["config"].pop("calibration", None)
            out["calibration_digest"] = self.calibration.digest()
        return out


def load_background(path: str | Path, width: int, height: int) -> np.ndarray:
    """Load an image file as a sensor background ``[height, width, 3]`` uint8, resized when needed."""
    from PIL import Image, UnidentifiedImageError

    p = Path(path).expanduser()
    if not p.is_file():
        raise TnfError(f"sensor background_image not found: {p}")
    try:
        with Image.open(p) as im:
            im = im.convert("RGB")
            if im.size != (width, height):
                im = im.resize((width, height), Image.Resampling.BILINEAR)
            return np.asarray(im, dtype=np.uint8).copy()
    except (UnidentifiedImageError, OSError) as e:
        raise TnfError(f"sensor background_image {p} is not a readable image: {e}") from None


def _smooth_noise(rng: np.random.Generator, h: int, w: int, cells: int) -> np.ndarray:
    """Smooth value noise ``[h, w]`` in about [-1, 1]: a coarse random grid, bilinearly upsampled."""
    gh, gw = cells + 1, max(2, round(cells * w / h)) + 1
    grid = rng.uniform(-1, 1, size=(gh, gw))
    ys = np.linspace(0, gh - 1, h)
    xs = np.linspace(0, gw - 1, w)
    y0 = np.clip(ys.astype(int), 0, gh - 2)
    x0 = np.clip(xs.astype(int), 0, gw - 2)
    fy = (ys - y0)[:, None]
    fx = (xs - x0)[None, :]
    g = grid
    return (
        g[y0][:, x0] * (1 - fy) * (1 - fx)
        + g[y0 + 1][:, x0] * fy * (1 - fx)
        + g[y0][:, x0 + 1] * (1 - fy) * fx
        + g[y0 + 1][:, x0 + 1] * fy * fx
    )
