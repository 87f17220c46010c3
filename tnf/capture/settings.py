"""The capture stage's settings (``cfg.capture``), in a module of their own so that the start-up check of a
config (``tnf.stages.settings``) validates them without importing the renderer. ``tnf.capture`` re-exports
:class:`CaptureConfig`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from tnf.registry import FROM_YAML, yaml_defaults


@dataclass
@yaml_defaults("capture/default")
class CaptureConfig:
    """Settings of the capture stage (``cfg.capture``)."""

    views: Literal["sphere", "hemisphere"] = FROM_YAML
    """Training camera layout: evenly on a whole sphere, or uniformly in an azimuth/elevation range."""
    num_views: int = FROM_YAML
    """Number of training views per object."""
    num_test_views: int = FROM_YAML
    """Number of held-out test views per object (a different set of poses)."""
    resolution: int = FROM_YAML
    """Image width and height in pixels."""
    fov_deg: float = FROM_YAML
    """Horizontal (= vertical) field of view in degrees."""
    fill: float = FROM_YAML
    """Fraction of the image width the object's bounding sphere spans; sets the camera distance."""
    distance: float | None = FROM_YAML
    """Camera distance from the origin in metres; null: from ``fill``, the object's size and the fov."""
    min_elevation_deg: float = FROM_YAML
    """Lowest camera elevation above the xy plane for ``hemisphere`` views, degrees."""
    max_elevation_deg: float = FROM_YAML
    """Highest camera elevation for ``hemisphere`` views, degrees."""
    min_azimuth_deg: float = FROM_YAML
    """Start of the azimuth range for ``hemisphere`` views, degrees."""
    max_azimuth_deg: float = FROM_YAML
    """End of the azimuth range for ``hemisphere`` views, degrees."""
    background: tuple[float, float, float] = FROM_YAML
    """RGB background colour in [0, 1] (the PNGs' colour where alpha is 0)."""
    ambient: float = FROM_YAML
    """Ambient light level in [0, 1]."""
    light_intensity: float = FROM_YAML
    """Strength of the key directional light (pyrender units); fill and rim lights are fractions of it."""
    antialias: int = FROM_YAML
    """Multisample anti-aliasing samples of the colour images: 0 samples each pixel at its centre, so colour,
    alpha and depth agree with one ray per pixel; 4 or 8 smooth the silhouettes at 3-4x the CPU cost."""

    def validate(self) -> None:
        if self.num_views < 1 or self.num_test_views < 0:
            raise ValueError(
                f"num_views must be >= 1 and num_test_views >= 0, got {self.num_views}, {self.num_test_views}"
            )
        if not 8 <= self.resolution <= 4096:
            raise ValueError(f"resolution must be in 8..4096 pixels, got {self.resolution}")
        if not 1.0 < self.fov_deg < 170.0:
            raise ValueError(f"fov_deg must be in (1, 170) degrees, got {self.fov_deg}")
        if not 0.05 <= self.fill <= 1.0:
            raise ValueError(f"fill must be in [0.05, 1], got {self.fill}")
        if self.distance is not None and self.distance <= 0:
            raise ValueError(f"distance must be > 0 metres or null, got {self.distance}")
        if not -90.0 <= self.min_elevation_deg <= self.max_elevation_deg <= 90.0:
            raise ValueError(
                f"need -90 <= min_elevation_deg <= max_elevation_deg <= 90, got "
                f"{self.min_elevation_deg}, {self.max_elevation_deg}"
            )
        if not 0 <= self.antialias <= 16:
            raise ValueError(f"antialias must be in 0..16 samples, got {self.antialias}")
        if any(not 0.0 <= c <= 1.0 for c in self.background):
            raise ValueError(f"background must be RGB in [0, 1], got {list(self.background)}")
