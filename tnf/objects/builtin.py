"""``builtin``: a procedural library of rigid household-like objects, made by code with trimesh.

Every object is deterministic, 5-25 cm in size (the 5 mm bearing ball apart), in metres, z up, coloured per
vertex, and carries surface detail at the scale a fingertip sensor feels (2-20 mm): ridges, knurling, threads,
grooves, dimples, raised marks, holes, and both sharp and rounded edges, so that touches of different objects
look different.
Meshes are closed (watertight) and kept to a moderate triangle count so that ray casting and rendering stay
fast. Each object is generated once per process and copied on every ``load``. The makers are in
``tnf.objects.catalogue``, one module per family; the building blocks (revolved profiles, extrusions, booleans,
displacements, colours) are in ``tnf.objects.modelling``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from tnf.objects import ObjectSource
from tnf.objects.catalogue import containers, food, household, tools, toys
from tnf.registry import FROM_YAML, yaml_defaults

# name -> generator. `ball` and `box` stay cheap: the tiny debug config uses them.
MAKERS: dict[str, Callable[[], Any]] = {
    "apple": food.apple,
    "ball": toys.ball,
    "banana": food.banana,
    "bearing_ball": toys.bearing_ball,
    "bolt": tools.bolt,
    "bottle": containers.bottle,
    "bowl": containers.bowl,
    "box": toys.box_,
    "brick": toys.brick,
    "can": containers.can,
    "candle": household.candle,
    "cereal_box": containers.cereal_box,
    "cheese_grater": tools.cheese_grater,
    "chess_pawn": toys.chess_pawn,
    "cucumber": food.cucumber,
    "die": toys.die,
    "donut": food.donut,
    "flashlight": tools.flashlight,
    "gear": tools.gear,
    "golf_ball": toys.golf_ball,
    "hammer": tools.hammer,
    "hex_nut": tools.hex_nut,
    "jar": containers.jar,
    "lemon": food.lemon,
    "marker": tools.marker,
    "mug": containers.mug,
    "paper_cup": containers.paper_cup,
    "pencil": tools.pencil,
    "pepper": food.pepper,
    "pill_bottle": containers.pill_bottle,
    "polish_tin": containers.polish_tin,
    "puzzle_cube": toys.puzzle_cube,
    "rolling_pin": tools.rolling_pin,
    "shampoo": containers.shampoo,
    "soap_bar": household.soap_bar,
    "sponge": household.sponge,
    "spray_can": containers.spray_can,
    "star_block": toys.star_block,
    "tape_roll": household.tape_roll,
    "tennis_ball": toys.tennis_ball,
    "traffic_cone": toys.traffic_cone,
    "vase": containers.vase,
    "wine_bottle": containers.wine_bottle,
    "wrench": tools.wrench,
}


@functools.cache
def _make(name: str):
    mesh = MAKERS[name]()
    mesh.metadata["name"] = name
    return mesh


def describe(name: str) -> str:
    """The one-line description of built-in object ``name``."""
    doc = (MAKERS[name].__doc__ or "").strip().splitlines()
    return doc[0] if doc else name


class Builtin(ObjectSource):
    """Procedural household objects (bottles, cans, mugs, tools, fruit...) with fingertip-scale detail."""

    @dataclass
    @yaml_defaults("objects/builtin")
    class Config:
        scale: float = FROM_YAML
        """Multiplies every object's size (1.0: objects are 5-25 cm)."""

        def validate(self) -> None:
            if not self.scale > 0:
                raise ValueError(f"scale must be > 0, got {self.scale}")

    name = "builtin"

    def __init__(self, cfg: Config | None = None):
        self.cfg = cfg or Builtin.Config()

    def names(self) -> list[str]:
        return sorted(MAKERS)

    def where(self, name: str) -> str:
        where = MAKERS[name].__module__.replace(".", "/") + ".py" if name in MAKERS else "tnf/objects/catalogue/"
        return f"builtin object {name!r} ({where})"

    def _load(self, name: str):
        mesh = _make(name).copy()
        if self.cfg.scale != 1.0:
            mesh.apply_scale(self.cfg.scale)
        return mesh
