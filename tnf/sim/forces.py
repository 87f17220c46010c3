"""Touches at many forces: the force range each touch's force is drawn from, and the held-out force bands.

``touch.force_range`` (null: every touch presses with ``touch.force``) names a training range ``[min, max]``
newtons, a distribution over it and two held-out bands:

- ``interpolation``: a band inside the range that no training or validation touch uses;
- ``extrapolation``: a band above the range.

Training and validation touches draw their force from the range without the interpolation band. Novel-view
touches are spread evenly over three bands in turn (``train``, ``interpolation``, ``extrapolation``), so every
test split holds touches in each band. Bands are fixed in the config, before any result.

A range or band left null comes from the sensor's gel stiffness: the Digit's 1-8 N scaled by the plane-strain
modulus ``E / (1 - nu^2)`` of the sensor's elastomer against the Digit's (a stiffer gel needs more force for the
same press); the interpolation band is the range's fourth seventh (4-5 N on the Digit), the extrapolation band
runs from max to 1.25 max.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from tnf.errors import TnfError

BANDS = ("train", "interpolation", "extrapolation")
"""Force bands, in the order novel-view touches cycle through them."""
DISTRIBUTIONS = ("uniform", "log_uniform")
DIGIT_RANGE = (1.0, 8.0)
"""The Digit's default training range, newtons."""
DIGIT_MODULUS = 3.0e5 / (1 - 0.48**2)
"""The Digit gel's plane-strain modulus ``E / (1 - nu^2)``, pascals (conf/sensor/digit.yaml)."""


def _number(x: Any, what: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise TnfError(f"{what}: expected a number of newtons, got {x!r}")
    v = float(x)
    if not math.isfinite(v):
        raise TnfError(f"{what}: expected a finite force, got {v}")
    if v < 0:
        raise TnfError(f"{what}: a force must be >= 0 N, got {v}")
    return v


def check_force_value(x: Any, what: str) -> float:
    """``x`` as a force in newtons; one-line TnfError for a non-number, NaN, infinity or a negative force."""
    return _number(x, what)


def _band(x: Any, what: str) -> tuple[float, float]:
    if not isinstance(x, Sequence) or isinstance(x, str) or len(x) != 2:
        raise TnfError(f"{what}: expected [low, high] newtons, got {x!r}")
    lo, hi = _number(x[0], what), _number(x[1], what)
    if not lo < hi:
        raise TnfError(f"{what}: low must be below high, got [{lo}, {hi}]")
    return lo, hi


@dataclass(frozen=True)
class ForcePlan:
    """Where each touch's force comes from: a training range, a distribution and two held-out bands (newtons)."""

    min: float
    max: float
    dist: str
    interpolation: tuple[float, float]
    extrapolation: tuple[float, float]

    def describe(self) -> dict[str, Any]:
        """The plan as plain JSON (recorded in touch and dataset manifests)."""
        return {
            "min": self.min,
            "max": self.max,
            "dist": self.dist,
            "interpolation": list(self.interpolation),
            "extrapolation": list(self.extrapolation),
            "unit": "N",
        }

    @classmethod
    def from_record(cls, rec: Mapping[str, Any]) -> ForcePlan:
        """A plan from ``describe()``'s output."""
        return cls(
            float(rec["min"]),
            float(rec["max"]),
            str(rec["dist"]),
            (float(rec["interpolation"][0]), float(rec["interpolation"][1])),
            (float(rec["extrapolation"][0]), float(rec["extrapolation"][1])),
        )

    def _draw(self, rng: np.random.Generator, n: int, lo: float, hi: float) -> np.ndarray:
        if self.dist == "log_uniform":
            return np.exp(rng.uniform(math.log(lo), math.log(hi), n))
        return rng.uniform(lo, hi, n)

    def training_forces(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``[n]`` forces from the training range without the interpolation band (training and validation)."""
        a, b = self.interpolation
        # Draw over the range with the band cut out: a draw above the band's low end is moved past it.
        if self.dist == "log_uniform":
            lo, hi, ca, cb = (math.log(v) for v in (self.min, self.max, a, b))
            u = rng.uniform(lo, hi - (cb - ca), n)
            return np.exp(np.where(u >= ca, u + (cb - ca), u))
        u = rng.uniform(self.min, self.max - (b - a), n)
        return np.where(u >= a, u + (b - a), u)

    def test_forces(self, rng: np.random.Generator, n: int, start: int = 0) -> tuple[np.ndarray, list[str]]:
        """``[n]`` forces for held-out touches, cycling through ``BANDS`` from the ``start``-th; and their bands."""
        bands = [BANDS[(start + i) % len(BANDS)] for i in range(n)]
        out = np.empty(n)
        for name in BANDS:
            idx = [i for i, b in enumerate(bands) if b == name]
            if not idx:
                continue
            if name == "train":
                out[idx] = self.training_forces(rng, len(idx))
            else:
                out[idx] = self._draw(rng, len(idx), *getattr(self, name))
        return out, bands

    def band_of(self, forces: np.ndarray | Sequence[float]) -> list[str]:
        """The band of each force (newtons): interpolation, extrapolation, train (in the range otherwise), or
        ``outside`` (below the range, or above it but below or beyond the extrapolation band)."""
        out = []
        for f in np.asarray(forces, dtype=np.float64).ravel():
            if self.interpolation[0] <= f <= self.interpolation[1]:
                out.append("interpolation")
            elif self.extrapolation[0] < f <= self.extrapolation[1] or (f == self.extrapolation[0] > self.max):
                out.append("extrapolation")
            elif self.min <= f <= self.max:
                out.append("train")
            else:
                out.append("outside")
        return out

    def adjacent(self, forces: np.ndarray | Sequence[float]) -> np.ndarray:
        """[N] bool: training forces within one interpolation-band width below or above that band (3-4 and 5-6 N
        for 4-5 N): the trained forces to compare the held-out band with, at a similar press."""
        f = np.asarray(forces, dtype=np.float64).ravel()
        a, b = self.interpolation
        w = b - a
        return ((f >= max(self.min, a - w)) & (f < a)) | ((f > b) & (f <= min(self.max, b + w)))

    def sweep(self, n: int = 6) -> list[float]:
        """``n`` forces from the range's minimum to the extrapolation band's top, evenly spaced (newtons)."""
        return [round(float(v), 3) for v in np.linspace(self.min, self.extrapolation[1], n)]


def default_range(sensor: Any) -> tuple[float, float]:
    """The training range of ``sensor`` from its gel's stiffness: the Digit's scaled by the plane-strain modulus."""
    c = sensor.cfg
    k = (c.young_modulus / (1 - c.poisson_ratio**2)) / DIGIT_MODULUS
    return round(DIGIT_RANGE[0] * k, 3), round(DIGIT_RANGE[1] * k, 3)


def force_plan(spec: Any, sensor: Any) -> ForcePlan | None:
    """The plan of a ``touch.force_range`` section as plain data (None when it is null), checked: one-line
    TnfError for a negative or non-finite force, min not below max, an unknown distribution, an interpolation
    band not inside the range, an extrapolation band not above it, or a force outside the sensor's force range."""
    if spec is None:
        return None
    if not isinstance(spec, Mapping):
        raise TnfError(f"touch.force_range: expected a section {{min, max, dist, ...}} or null, got {spec!r}")
    known = {"min", "max", "dist", "interpolation", "extrapolation"}
    unknown = sorted(set(spec) - known)
    if unknown:
        raise TnfError(f"touch.force_range: unknown setting {unknown[0]!r}; settings: {', '.join(sorted(known))}")
    d_lo, d_hi = default_range(sensor)
    lo = d_lo if spec.get("min") is None else _number(spec["min"], "touch.force_range.min")
    hi = d_hi if spec.get("max") is None else _number(spec["max"], "touch.force_range.max")
    if not lo < hi:
        raise TnfError(f"touch.force_range: min ({lo} N) must be below max ({hi} N)")
    if lo <= 0:
        raise TnfError(f"touch.force_range.min: a press needs a force > 0 N, got {lo}")
    dist = str(spec.get("dist") or "uniform")
    if dist not in DISTRIBUTIONS:
        raise TnfError(f"touch.force_range.dist must be one of {', '.join(DISTRIBUTIONS)}, got {dist!r}")
    span = hi - lo
    interp = (
        (round(lo + 3 * span / 7, 3), round(lo + 4 * span / 7, 3))
        if spec.get("interpolation") is None
        else _band(spec["interpolation"], "touch.force_range.interpolation")
    )
    extra = (
        (hi, round(1.25 * hi, 3))
        if spec.get("extrapolation") is None
        else _band(spec["extrapolation"], "touch.force_range.extrapolation")
    )
    if not lo < interp[0] < interp[1] < hi:
        raise TnfError(
            f"touch.force_range.interpolation [{interp[0]}, {interp[1]}] must lie strictly inside the range "
            f"[{lo}, {hi}]"
        )
    if extra[0] < hi:
        raise TnfError(f"touch.force_range.extrapolation [{extra[0]}, {extra[1]}] must start at or above max ({hi} N)")
    sensor.check_force(lo, "touch.force_range.min")
    band = "" if spec.get("extrapolation") is not None else " (null: [max, 1.25 max])"
    sensor.check_force(extra[1], f"touch.force_range.extrapolation [{extra[0]}, {extra[1]}]{band}")
    return ForcePlan(lo, hi, dist, interp, extra)


def force_sampler(plan: ForcePlan, split: str, seed: int) -> Any:
    """The force sampler of one split's touches for ``tnf.sim.touch.collect``: ``k -> [k]`` newtons. Training and
    validation touches draw from the training range; novel-view touches cycle through ``BANDS``. Its own random
    stream (from ``seed``), so the poses are drawn as they are at a fixed force."""
    rng = np.random.default_rng([seed, 0xF0])
    drawn = [0]

    def sample(k: int) -> np.ndarray:
        if split == "novel_view":
            out, _ = plan.test_forces(rng, k, start=drawn[0])
        else:
            out = plan.training_forces(rng, k)
        drawn[0] += k
        return out.astype(np.float32)

    return sample


def requested_forces(value: Any, trained_with_force: bool, model: str, default: float) -> list[float] | str | None:
    """What ``generate.touch_force`` asks for: a list of forces (newtons; a number is one, a list or a string
    ``"low:high:count"`` sweeps), ``"sim"`` (each touch's own recorded force) or None (a model without force).
    A model trained with force and no request generates at ``default`` (``touch.force``). One-line TnfError for a
    negative or NaN force, a bad sweep, or a request to a model that was not trained with force."""
    if value is None:
        return [check_force_value(default, "touch.force")] if trained_with_force else None
    if not trained_with_force:
        raise TnfError(
            f"generate.touch_force={value}: model {model!r} was not trained with force (generator.force=none); "
            "train one with generator=tn_cgan_force on pairs made with pair.force=true, or leave it unset"
        )
    if isinstance(value, str):
        if value == "sim":
            return "sim"
        parts = value.split(":")
        try:
            lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
        except (IndexError, ValueError):
            if _is_float(value):
                raise TnfError(
                    f"generate.touch_force: got the string {value!r}; give the force as a number, without quotes "
                    f"(generate.touch_force={value.strip()})"
                ) from None
            raise TnfError(
                f"generate.touch_force: expected newtons, a list, 'low:high:count' or sim, got {value!r}"
            ) from None
        if len(parts) != 3 or n < 1 or not lo <= hi:
            raise TnfError(f"generate.touch_force={value}: a sweep 'low:high:count' needs low <= high and count >= 1")
        for v in (lo, hi):
            check_force_value(v, "generate.touch_force")
        out = [float(v) for v in np.linspace(lo, hi, n)]
    else:
        values = list(value) if isinstance(value, Sequence) else [value]
        if not values:
            raise TnfError("generate.touch_force: an empty list of forces")
        out = [check_force_value(v, "generate.touch_force") for v in values]
    if any(v == 0 for v in out):
        raise TnfError("generate.touch_force: a press needs a force > 0 N, got 0")
    return out


def _is_float(text: str) -> bool:
    """Whether ``text`` reads as a finite number."""
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False
