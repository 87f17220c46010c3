"""The simulator interface: what every tactile simulator implements, in-tree (``warp_gel``) or from a plugin.

A simulator is registered in ``SIMULATORS`` (entry-point group ``tnf.simulators``) and built as
``Simulator(cfg, sensor=sensor, device=device)``. It presses the sensor onto an object and returns the
touches as a :class:`TouchBatch`. ``tnf.testing.SimulatorContract`` checks an implementation.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from tnf.sensors.base import Sensor


@dataclass
class TouchBatch:
    """Results of B touches of one object; arrays are NumPy on the host.

    Attributes:
        images: ``[B, H, W, 3]`` uint8 tactile images.
        indentation: ``[B, H, W]`` float32, metres the gel surface moved toward the camera.
        contact: ``[B, H, W]`` bool, pixels where the gel touches the object.
        force: ``[B]`` float32 normal force reached, newtons (the target unless the press hit ``max_penetration``).
        penetration: ``[B]`` float32 metres the sensor advanced past first contact.
        hit: ``[B]`` bool, whether the gel touched the object at all (no hit: image = background + noise).
        advance: ``[B]`` float32 metres from the start pose to first contact (inf without a hit).
        contact_point: ``[B, 3]`` world position of the first contact (NaN without a hit).
        contact_c2w: ``[B, 4, 4]`` sensor pose (camera-to-world) while pressing.
    """

    images: np.ndarray
    indentation: np.ndarray
    contact: np.ndarray
    force: np.ndarray
    penetration: np.ndarray
    hit: np.ndarray
    advance: np.ndarray
    contact_point: np.ndarray
    contact_c2w: np.ndarray


class Simulator(ABC):
    """Base class of tactile simulators: presses a sensor onto objects and renders its images.

    A subclass declares a nested ``Config`` dataclass and sets, in ``__init__(cfg, sensor, device)``:
    ``cfg``, ``sensor`` and ``background`` (``[H, W, 3]`` uint8, the image without contact or noise). A Config
    field that changes only how fast it runs, not its touches, says so (``yaml_field(identity=False)``): item
    keys leave it out.
    ``device`` is a warp device name (``cpu``, ``cuda:0``); a simulator that runs elsewhere may ignore it.
    """

    cfg: Any
    sensor: Sensor
    background: np.ndarray

    @abstractmethod
    def press(self, mesh: Any, start_c2w: np.ndarray, force: float | np.ndarray, seed: int = 0) -> TouchBatch:
        """Press the sensor onto ``mesh`` from B start poses with a constant normal force.

        Args:
            mesh: the object (trimesh.Trimesh, metres, world frame).
            start_c2w: ``[B, 4, 4]`` sensor poses (camera-to-world, OpenGL: the sensor advances along its -z).
            force: target normal force, newtons (scalar or ``[B]``), within the sensor's ``force_range``.
            seed: seed of the image noise: the same seed gives the same images.
        """

    @abstractmethod
    def press_heights(
        self,
        gaps: np.ndarray,
        force: float | np.ndarray | None = None,
        seed: int = 0,
        penetration: float | np.ndarray | None = None,
    ) -> TouchBatch:
        """Press onto B surfaces given as height fields in the sensor's pixel grid, instead of a mesh.

        Args:
            gaps: ``[B, H, W]`` metres from each pixel's undeformed gel point along the sensor's axis (-z) to
                the surface; non-finite where the pixel sees no surface.
            force: target normal force, newtons (scalar or ``[B]``); give this or ``penetration``.
            seed: seed of the image noise.
            penetration: metres past first contact (scalar or ``[B]``); ``force`` then reports the force it took.
                A penetration deeper than the sensor's ``max_penetration`` raises a TnfError (a press by
                ``force`` stops there instead, and reports the force it reached).

        Returns:
            The touches, with the sensor frame as the world frame (the start pose is the identity).
        """


def simulator_key(spec: Mapping[str, Any]) -> dict[str, Any]:
    """A simulator's config node (``{"name": ..., **fields}``) as item keys record it: its validated Config's
    identity (``tnf.artifacts.identity``)."""
    from tnf.artifacts import identity
    from tnf.registry import SIMULATORS, split_spec

    name, params = split_spec(spec, "simulator")
    return {"name": name, **identity(SIMULATORS.config(name, params))}
