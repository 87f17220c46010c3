"""Fit a sensor's optics to real indenter presses: the library behind ``tnf calibrate``.

The fit, for the training presses of a press folder:

1. Frames and background are resized to the sensor's image size; the sensor's pixel size must match the
   recording's (``mm_per_pixel`` scaled by the resize), so the indenter has its real size in the image.
2. The simulator presses a sphere of the indenter's radius, at each press's centre and depth, into the gel
   (``WarpGel.press_heights`` to a penetration): the deformed surface, with the gel's fall-off around the contact.
3. The shading table (``Calibration.table``) is the linear least-squares fit of ``real - background`` to the
   blurred table reading at each pixel's surface slope, over the pixels near each contact, with a smoothness
   penalty (second differences over the table) and a small ridge that fill slopes no press showed.
4. The fall-off, a factor on the presses' depths and the blur are chosen from fixed candidates by a coordinate
   search: each fall-off at the first depth factor and the middle blur, then each depth factor, then each blur,
   by the mean squared error over the training presses' contact regions. Each candidate costs one table fit
   (a linear solve). The depth factor corrects hand-drawn contact circles, which tend to miss the gel's outer
   slope; it applies to presses (``depth_scale`` in the record), not to the simulator.

Frames, depths and centres come from :mod:`tnf.real.presses`; the table is read by ``warp_gel`` on the device.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tnf.errors import TnfError
from tnf.real import realism, report
from tnf.real.presses import PressSet, SensorPresses, at_sensor_size, check_indices, disk_masks, sphere_gaps
from tnf.registry import FROM_YAML, SIMULATORS, at_least, yaml_defaults
from tnf.sensors.base import Sensor
from tnf.sensors.calibration import Calibration, table_cells


@dataclass
@yaml_defaults("calibrate/default", node="fit")
class FitSettings:
    """How the optics are fitted (``calibrate.fit`` in the config)."""

    table_size: int = FROM_YAML
    """Table nodes per slope axis."""
    max_slope: float = FROM_YAML
    """Half-width of the table's slope grid (dimensionless); steeper slopes read the edge."""
    slope_power: float = FROM_YAML
    """Node spacing along each slope axis: regular in ``sign(s) |s / max_slope|^slope_power`` (1: regular)."""
    falloffs: list[float] = FROM_YAML
    """Candidate gel fall-off lengths, multiples of the sensor's gel thickness."""
    depth_scales: list[float] = FROM_YAML
    """Candidate factors on each press's depth: hand-drawn contact circles tend to miss the gel's outer slope."""
    blurs: list[float] = FROM_YAML
    """Candidate blur sigmas of the change image, pixels at the sensor's size."""
    smoothness: float = FROM_YAML
    """Weight of the second-difference penalty over the table."""
    ridge: float = FROM_YAML
    """Weight pulling table entries toward zero (matters only where no press reached)."""
    fit_scale: float = FROM_YAML
    """Pixels within this multiple of a press's contact radius enter the fit."""
    region_scale: float = FROM_YAML
    """The contact region, scored in the search and in the realism report: this multiple of the contact radius."""
    refine_radius: int = FROM_YAML
    """Training presses move up to this many pixels (sensor size) to where the first fit's pattern best matches
    their frames, and the search runs again; 0 keeps the annotated centres. Held-out presses never move."""

    def validate(self) -> None:
        if not (math.isfinite(self.slope_power) and 0 < self.slope_power <= 1):
            raise ValueError(f"slope_power must be in (0, 1], got {self.slope_power}")
        if self.table_size < 3:
            raise ValueError(f"table_size must be >= 3, got {self.table_size}")
        for name in ("max_slope", "smoothness", "fit_scale", "region_scale"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")
        if isinstance(self.refine_radius, bool) or not isinstance(self.refine_radius, int) or self.refine_radius < 0:
            raise ValueError(f"refine_radius must be a whole number of pixels >= 0, got {self.refine_radius}")
        if not (math.isfinite(self.ridge) and self.ridge >= 0):
            raise ValueError(f"ridge must be a finite number >= 0, got {self.ridge}")
        if not self.falloffs or not all(math.isfinite(f) and f > 0 for f in self.falloffs):
            raise ValueError(f"falloffs must be a non-empty list of numbers > 0, got {self.falloffs}")
        if not self.depth_scales or not all(math.isfinite(d) and d > 0 for d in self.depth_scales):
            raise ValueError(f"depth_scales must be a non-empty list of numbers > 0, got {self.depth_scales}")
        if not self.blurs or not all(math.isfinite(b) and b >= 0 for b in self.blurs):
            raise ValueError(f"blurs must be a non-empty list of numbers >= 0, got {self.blurs}")


@dataclass
@yaml_defaults("calibrate/default")
class CalibrateSettings:
    """The ``calibrate`` section: which presses fit the sensor's optics, which score it, and how it is fitted."""

    presses: str = FROM_YAML
    """A press folder, or ``taxim:SENSOR`` for the recording the taxim package ships."""
    name: str = FROM_YAML
    """The calibration's folder under ``<data_root>/calibration/<sensor>/``."""
    train: list[int] = FROM_YAML
    """Presses the fit sees."""
    test: list[int] = FROM_YAML
    """Held-out presses the realism report scores."""
    grid_presses: int = FROM_YAML
    """Rows of the realism figure (held-out presses, cropped around the contact)."""
    fit: FitSettings = FROM_YAML
    """How the optics are fitted."""

    def validate(self) -> None:
        at_least(self, 0, "grid_presses")


def press_surfaces(sensor: Sensor, simulator: dict[str, Any], sp: SensorPresses, radius_m: float) -> np.ndarray:
    """Indentation ``[N, H, W]`` (metres toward the camera) of the sphere pressed to each press's depth."""
    sim = SIMULATORS.build(simulator, sensor=sensor, device="cpu")
    return sim.press_heights(sphere_gaps(sensor, sp.centers, radius_m), penetration=sp.depths).indentation


def _bilinear(slopes: np.ndarray, n: int, max_slope: float, power: float) -> tuple[np.ndarray, np.ndarray]:
    """Table node indices ``[P, 4]`` and weights ``[P, 4]`` of slopes ``[P, 2]`` (as ``Calibration.shade``)."""
    i0, j0, ay, ax = table_cells(slopes, n, max_slope, power)
    idx = np.stack([i0 * n + j0, i0 * n + j0 + 1, (i0 + 1) * n + j0, (i0 + 1) * n + j0 + 1], 1)
    w = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], 1)
    return idx, w


def _smoothness(n: int) -> np.ndarray:
    """``D^T D`` of the second differences along both axes of an ``n x n`` table."""
    rows = []
    for i in range(n):
        for j in range(n):
            for di, dj in ((1, 0), (0, 1)):
                if 0 < i < n - 1 if di else 0 < j < n - 1:
                    r = np.zeros(n * n)
                    r[(i - di) * n + j - dj] += 1
                    r[i * n + j] -= 2
                    r[(i + di) * n + j + dj] += 1
                    rows.append(r)
    d = np.array(rows)
    return d.T @ d


def _blur_matrix(n: int, sigma: float) -> np.ndarray:
    """``[n, n]`` matrix ``G`` with ``G @ v`` equal to ``gaussian_filter1d(v, sigma, mode="nearest")``."""
    from scipy.ndimage import gaussian_filter1d

    return gaussian_filter1d(np.eye(n), sigma, axis=0, mode="nearest")


class _Design:
    """Per-press crops of the unblurred design (table weights at each pixel's slope, minus the undeformed
    slope's) and the targets (real minus background), for one fall-off.

    A crop's design is a sparse ``[pixels, nodes]`` matrix ``W`` (at most eight weights per pixel). The blur is
    separable and linear: ``G = Gy (x) Gx``, so the blurred design's normal equations are ``W^T G^T G W`` and
    ``W^T G^T t``, and a prediction is ``G (W x)``: the blur runs on images and on ``W`` once per press as two
    small matrix products, never on a dense blurred copy of ``W``."""

    def __init__(self, sensor: Sensor, sp: SensorPresses, u: np.ndarray, st: FitSettings):
        from scipy.sparse import coo_matrix

        n, k = st.table_size, st.table_size**2
        h0 = sensor.gel_surface()
        s0 = sensor.surface_slopes(h0)
        slopes = sensor.surface_slopes(h0[None] - u)
        #: Per press: the design ``[pixels, nodes]`` (CSR), the target ``[pixels, 3]`` and the region mask.
        self.crops: list[tuple[Any, np.ndarray, np.ndarray]] = []
        self.bounds: list[tuple[int, int, int, int]] = []
        self._blurs: dict[tuple[int, float], tuple[np.ndarray, np.ndarray]] = {}
        hh, ww = h0.shape
        for b in range(len(u)):
            col, row = sp.centers[b]
            half = int(math.ceil(st.fit_scale * sp.radii[b])) + 2
            r0, r1 = max(0, int(row) - half), min(hh, int(row) + half + 1)
            c0, c1 = max(0, int(col) - half), min(ww, int(col) + half + 1)
            pixels = (r1 - r0) * (c1 - c0)
            self.bounds.append((r0, r1, c0, c1))
            rows, cols, vals = [], [], []
            for sl, sign in ((slopes[b, r0:r1, c0:c1], 1.0), (s0[r0:r1, c0:c1], -1.0)):
                idx, wt = _bilinear(sl.reshape(-1, 2), n, st.max_slope, st.slope_power)
                rows.append(np.repeat(np.arange(pixels), 4))
                cols.append(idx.reshape(-1))
                vals.append(sign * wt.reshape(-1))
            w = coo_matrix(
                (np.concatenate(vals).astype(np.float32), (np.concatenate(rows), np.concatenate(cols))),
                shape=(pixels, k),
            ).tocsr()  # repeated entries are summed
            target = sp.frames[b, r0:r1, c0:c1].astype(np.float32) - sp.background[r0:r1, c0:c1]
            rr, cc = np.mgrid[r0:r1, c0:c1]
            region = (cc - col) ** 2 + (rr - row) ** 2 <= (st.region_scale * sp.radii[b]) ** 2
            self.crops.append((w, target.reshape(-1, 3), region.reshape(-1)))

    def _blur_pair(self, size: int, blur: float) -> tuple[np.ndarray, np.ndarray]:
        """The blur matrix ``G`` ``[size, size]`` along one axis and ``G^T G`` (float32, for the design)."""
        if (size, blur) not in self._blurs:
            g = _blur_matrix(size, blur)
            self._blurs[size, blur] = (g, (g.T @ g).astype(np.float32))
        return self._blurs[size, blur]

    def _shape(self, b: int) -> tuple[int, int]:
        r0, r1, c0, c1 = self.bounds[b]
        return r1 - r0, c1 - c0

    def blurred(self, b: int, image: np.ndarray, blur: float, transpose: bool = False) -> np.ndarray:
        """Press ``b``'s crop image ``[pixels, C]`` blurred (``G v``; ``G^T v`` with ``transpose``), ``[pixels, C]``."""
        if blur <= 0:
            return image
        h, w = self._shape(b)
        gy, gx = self._blur_pair(h, blur)[0], self._blur_pair(w, blur)[0]
        if transpose:
            gy, gx = gy.T, gx.T
        along_rows = (gy @ image.reshape(h, -1)).reshape(h, w, -1)
        return np.matmul(gx, along_rows).reshape(h * w, -1)

    def fit(self, blur: float, st: FitSettings, reg: np.ndarray) -> tuple[np.ndarray, float]:
        """Table ``[n, n, 3]`` for this blur, and its mean squared error over the contact regions."""
        k = st.table_size**2
        ata = np.zeros((k, k))
        atb = np.zeros((k, 3))
        for b, (w, target, _) in enumerate(self.crops):
            if blur > 0:
                h, wd = self._shape(b)
                hy, hx = self._blur_pair(h, blur)[1], self._blur_pair(wd, blur)[1]
                q = np.matmul(hx, (hy @ w.toarray().reshape(h, -1)).reshape(h, wd, k))  # G^T G W, [h, w, k]
                ata += w.T @ q.reshape(-1, k)
            else:
                ata += (w.T @ w).toarray()
            atb += w.T @ self.blurred(b, target, blur, transpose=True)
        x = np.linalg.solve(ata + reg, atb)
        err, count = 0.0, 0
        for b, (w, target, region) in enumerate(self.crops):
            res = self.blurred(b, w @ x, blur)[region] - target[region]
            err += float((res**2).sum())
            count += res.size
        return x.reshape(st.table_size, st.table_size, 3).astype(np.float32), err / max(count, 1)

    def shifts(self, table: np.ndarray, blur: float, sp: SensorPresses, radius: int) -> np.ndarray:
        """Per press, the whole-pixel shift ``[N, 2]`` ``(columns, rows)`` of the frame's change (real minus
        background) within ``radius`` that best matches the fitted pattern, by squared error over the crop."""
        x = table.reshape(-1, 3).astype(np.float64)
        change = sp.frames.astype(np.float32) - sp.background
        hh, ww = change.shape[1:3]
        out = np.zeros((len(self.crops), 2))
        for b, ((w, _, _), (r0, r1, c0, c1)) in enumerate(zip(self.crops, self.bounds)):
            pred = self.blurred(b, w @ x, blur).reshape(r1 - r0, c1 - c0, 3)
            best = (math.inf, 0, 0)
            for dr in range(-radius, radius + 1):
                for dc in range(-radius, radius + 1):
                    if r0 + dr < 0 or c0 + dc < 0 or r1 + dr > hh or c1 + dc > ww:
                        continue
                    err = float(((change[b, r0 + dr : r1 + dr, c0 + dc : c1 + dc] - pred) ** 2).mean())
                    if err < best[0]:
                        best = (err, dc, dr)
            out[b] = best[1:]
        return out


def feasible_depth_scales(
    scales: Sequence[float], sp: SensorPresses, sensor: Sensor, radius_m: float
) -> tuple[list[float], list[str]]:
    """The depth factors that press every press of ``sp`` no deeper than the sensor's ``max_penetration`` and
    less deep than the indenter's radius ``radius_m``, and one line for each factor left out.

    Raises a one-line TnfError when no factor is left."""
    k = int(np.argmax(sp.depths))
    deepest, press = float(sp.depths[k]), sp.indices[k]
    gel = float(sensor.cfg.max_penetration)

    def past(depth: float) -> str | None:
        """What a press ``depth`` (metres) deep goes past, if anything."""
        if depth > gel:
            return f"the sensor's max_penetration {1e3 * gel:g} mm"
        if depth >= radius_m:
            return f"the indenter's radius {1e3 * radius_m:g} mm"
        return None

    kept = [float(s) for s in scales if past(deepest * s) is None]
    skipped = [
        f"calibrate.fit.depth_scales: x{s:g} left out: press {press}, {1e3 * deepest:.2f} mm deep, would go "
        f"{1e3 * deepest * s:.2f} mm, past {past(deepest * s)}"
        for s in scales
        if past(deepest * s) is not None
    ]
    if not kept:
        smallest = float(min(scales))
        raise TnfError(
            f"calibrate.fit.depth_scales: every factor of {list(scales)} presses too deep: x{smallest:g} takes press "
            f"{press} ({1e3 * deepest:.2f} mm deep) past {past(deepest * smallest)}; add a smaller factor"
        )
    return kept, skipped


class _Search:
    """The search over fall-off, depth factor and blur: each candidate's table fitted once and remembered."""

    def __init__(
        self,
        sensor: Sensor,
        sp: SensorPresses,
        simulator: dict[str, Any],
        radius_m: float,
        settings: FitSettings,
        on_step: Callable[[str], None] | None = None,
    ):
        self.sensor, self.sp, self.simulator, self.radius, self.settings = sensor, sp, simulator, radius_m, settings
        n = settings.table_size
        self.reg = settings.smoothness * _smoothness(n) + settings.ridge * np.eye(n * n)
        self.mid_blur = sorted(settings.blurs)[len(settings.blurs) // 2]
        self.depth_scales, self.skipped = feasible_depth_scales(settings.depth_scales, sp, sensor, radius_m)
        self.tried: list[dict[str, float]] = []
        self.designs: dict[tuple[float, float], _Design] = {}
        self.results: dict[tuple[float, float, float], tuple[np.ndarray, float]] = {}
        self.on_step = on_step

    def design(self, falloff: float, scale: float) -> _Design:
        """The design of the presses at depth factor ``scale`` with fall-off ``falloff`` (the last one kept)."""
        if (falloff, scale) not in self.designs:
            spec = {**self.simulator, "falloff": float(falloff)}
            scaled = dataclasses.replace(self.sp, depths=self.sp.depths * scale)
            surfaces = press_surfaces(self.sensor, spec, scaled, self.radius)
            self.designs.clear()  # one at a time: each holds a few hundred MB of crops
            self.designs[falloff, scale] = _Design(self.sensor, self.sp, surfaces, self.settings)
        return self.designs[falloff, scale]

    def trial(self, falloff: float, scale: float, blur: float) -> float:
        """The training region's MSE of one candidate."""
        key = (falloff, scale, blur)
        if key not in self.results:
            self.results[key] = self.design(falloff, scale).fit(blur, self.settings, self.reg)
            err = self.results[key][1]
            self.tried.append(
                {"falloff": float(falloff), "depth_scale": float(scale), "blur_sigma": float(blur), "region_mse": err}
            )
            if self.on_step is not None:
                self.on_step(f"falloff {falloff:g}, depth x{scale:g}, blur {blur:g}: MSE {err:.1f}")
        return self.results[key][1]

    def search(self) -> tuple[float, float, float]:
        """Fall-off at the first depth factor and the middle blur, then the depth factor, then the blur."""
        st, mid = self.settings, self.mid_blur
        f = min(st.falloffs, key=lambda f: self.trial(f, self.depth_scales[0], mid))
        d = min(self.depth_scales, key=lambda d: self.trial(f, d, mid))
        b = min(sorted(st.blurs, key=lambda b: b != mid), key=lambda b: self.trial(f, d, b))
        return f, d, b


def fit_calibration(
    presses: PressSet,
    sensor: Sensor,
    simulator: dict[str, Any],
    train: Sequence[int],
    settings: FitSettings,
    on_step: Callable[[str], None] | None = None,
) -> tuple[Calibration, dict[str, Any]]:
    """Fit the optics of ``sensor`` to the presses ``train`` (module docstring).

    Args:
        presses: a checked press folder.
        sensor: the sensor to calibrate (its geometry, gel and image size; its lights are not used).
        simulator: the simulator's spec ``{"name": "warp_gel", ...}`` (its ``falloff`` is searched).
        train: indices of the presses to fit.
        settings: the fit's settings.
        on_step: called with a short description after each candidate (a progress bar's advance).

    Returns:
        The calibration and a JSON-able record of the search (each candidate's error, the choice, seconds).
    """
    t0 = time.perf_counter()
    if sensor.cfg.calibration is not None:  # fit from the hand-set optics, not from an earlier calibration
        sensor = type(sensor)(dataclasses.replace(sensor.cfg, calibration=None))
    sp = at_sensor_size(presses, sensor, train)
    run = _Search(sensor, sp, simulator, presses.radius_mm * 1e-3, settings, on_step)
    falloff, scale, blur = run.search()
    moved = np.zeros((len(train), 2))
    if settings.refine_radius > 0:
        design = run.design(falloff, scale)
        moved = design.shifts(run.results[falloff, scale, blur][0], blur, run.sp, settings.refine_radius)
        run.sp = dataclasses.replace(run.sp, centers=run.sp.centers + moved)
        run.designs.clear()
        run.results.clear()
        falloff, scale, blur = run.search()
    sp, tried = run.sp, run.tried
    table, err = run.results[falloff, scale, blur]
    cal = Calibration(
        table=table,
        max_slope=float(settings.max_slope),
        slope_power=float(settings.slope_power),
        blur_sigma=float(blur),
        noise_std=0.0,  # the background is a real frame and carries the sensor's own noise
        falloff=float(falloff),
        background=sp.background,
    )
    info = {
        "train": list(train),
        "falloff": float(falloff),
        "blur_sigma": float(blur),
        "depth_scale": float(scale),
        "search": tried,
        "edges": run.skipped + search_edges(settings, falloff, scale, blur, run.depth_scales),
        "center_shifts_px": moved.tolist(),
        "train_region_mse": float(err),
        "frame_noise_std": frame_noise(sp),
        "settings": dataclasses.asdict(settings),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    return cal, info


def centre_shifts(
    presses: PressSet,
    sensor: Sensor,
    simulator: dict[str, Any],
    cal: Calibration,
    info: dict[str, Any],
    indices: Sequence[int],
    settings: FitSettings,
) -> np.ndarray:
    """Per press of ``indices``, the shift ``[N, 2]`` ``(columns, rows)``, in the recording's pixels, that moves
    its annotated centre to where the calibration's pattern best fits its frame: the search the fit runs on its
    training presses (``settings.refine_radius`` pixels at the sensor's size at most). A diagnostic: on held-out
    presses it reads their frames."""
    sp = at_sensor_size(presses, sensor, indices)
    deep = dataclasses.replace(sp, depths=sp.depths * info["depth_scale"])
    surfaces = press_surfaces(sensor, {**simulator, "falloff": info["falloff"]}, deep, presses.radius_mm * 1e-3)
    moved = _Design(sensor, sp, surfaces, settings).shifts(cal.table, info["blur_sigma"], sp, settings.refine_radius)
    return moved * presses.width / sensor.width


NO_CONTACT = "no contact (f0)"
UNCALIBRATED = "tnf uncalibrated"
CALIBRATED = "tnf calibrated"
"""Row names of the realism report (``tnf.real.report``)."""


def search_steps(settings: FitSettings) -> int:
    """How many candidates the search scores (a progress bar's total)."""
    one = len(settings.falloffs) + len(settings.depth_scales) + len(settings.blurs) - 2
    return 2 * one if settings.refine_radius > 0 else one


def search_edges(
    settings: FitSettings, falloff: float, scale: float, blur: float, depth_scales: Sequence[float] | None = None
) -> list[str]:
    """One line for each searched value that landed on the edge of its candidate list: the best value may lie
    beyond it. Blur 0 is no edge (a blur cannot be negative). ``depth_scales``: the factors searched (default:
    the settings'); beyond the largest one searched lie only factors left out as too deep, so it is no edge."""
    lines = []
    scales = settings.depth_scales if depth_scales is None else depth_scales
    too_deep = len(scales) < len(settings.depth_scales)
    for name, value, cands in (
        ("falloffs", falloff, settings.falloffs),
        ("depth_scales", scale, scales),
        ("blurs", blur, settings.blurs),
    ):
        if len(cands) < 2 or (name == "blurs" and value == 0):
            continue
        if value in (min(cands), max(cands)):
            side = "smallest" if value == min(cands) else "largest"
            if name == "depth_scales" and side == "largest" and too_deep:
                continue
            lines.append(
                f"calibrate.fit.{name}: the fit chose {value:g}, the {side} candidate; the best value may lie "
                f"beyond it: extend the list and calibrate again"
            )
    return lines


def frame_noise(sp: SensorPresses) -> float:
    """Pixel noise of one frame (8-bit units), from real minus background far from every contact: the
    difference of two noisy frames has twice a frame's variance."""
    far = ~disk_masks(sp.background.shape[:2], sp.centers, 4 * sp.radii)
    d = sp.frames.astype(np.float64) - sp.background
    d -= np.median(d[far], axis=0)
    mad = np.median(np.abs(d[far]))
    return float(1.4826 * mad / math.sqrt(2))


def calibration_rows(
    presses: PressSet,
    sensor: Sensor,
    cal: Calibration,
    info: dict[str, Any],
    simulator: dict[str, Any],
    test: Sequence[int],
    where: str,
) -> tuple[list[report.Row], SensorPresses]:
    """The realism report's rows of a calibration, on presses ``test``: the no-contact frame, the sensor's hand-set
    lights, the calibration at the sensor's size and rendered at the recording's. Also the presses at the
    sensor's size. Each simulator is placed at the annotated centres, without pixel noise, over the real
    background; ``info`` is :func:`fit_calibration`'s record (its depth factor)."""
    plain = type(sensor)(
        dataclasses.replace(sensor.cfg, calibration=None, background_image=str(presses.background_path))
    )
    calibrated = plain.calibrated(cal, where)
    sp = at_sensor_size(presses, plain, test)
    radius = presses.radius_mm * 1e-3
    scale = info["depth_scale"]
    rows = [report.Row(NO_CONTACT, np.stack([presses.background()] * len(test)))]
    rows.append(report.Row(UNCALIBRATED, *realism.render(plain, simulator, sp, radius)))
    rows.append(
        report.Row(
            f"{CALIBRATED}, {sensor.width}x{sensor.height}", *realism.render(calibrated, simulator, sp, radius, scale)
        )
    )
    native = realism.render_native(calibrated, simulator, presses, test, scale)
    rows.append(report.Row(f"{CALIBRATED}, {presses.width}x{presses.height}", *native))
    return rows, sp


def fit_summary(info: dict[str, Any], settings: FitSettings, size: str) -> list[str]:
    """Lines for a report: what the fit chose, in how long, and its warnings."""
    return [
        f"Fitted on presses {info['train']} in {info['seconds']:.1f} s: fall-off {info['falloff']:g} x thickness, "
        f"depth x{info['depth_scale']:g}, blur {info['blur_sigma']:g} px at {size}, table "
        f"{settings.table_size}x{settings.table_size} (slope power {settings.slope_power:g}), training centres "
        f"moved by {float(np.abs(info['center_shifts_px']).mean()):.1f} px on average; frame noise "
        f"{info['frame_noise_std']:.2f}.",
        "Every row uses the real background; uncalibrated is the sensor's hand-set lights. Held-out presses sit "
        "at their annotated centres.",
        *(f"Warning: {line}" for line in info["edges"]),
    ]


def calibrate_sensor(
    presses: PressSet,
    sensor: Sensor,
    simulator: dict[str, Any],
    train: Sequence[int],
    test: Sequence[int],
    settings: FitSettings,
    out: str | Path,
    grid_presses: int = 4,
    on_step: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Fit ``sensor``'s optics on presses ``train``, write the calibration into ``out`` and score realism on
    presses ``test``, before (the sensor's hand-set optics over the real background) and after calibration.

    Writes ``calibration.npz``, ``background.png`` and the realism report (:mod:`tnf.real.report`: the
    no-contact frame, uncalibrated, calibrated at the sensor's size and at the recording's). Returns the report's
    record, the fit's under ``"fit"``.
    """
    overlap = sorted(set(train) & set(test))
    if overlap:
        raise TnfError(f"calibrate: press {overlap[0]} is in both train and test")
    if not train or not test:
        raise TnfError("calibrate: train and test each need at least one press")
    check_indices(presses, train, "calibrate.train")
    check_indices(presses, test, "calibrate.test")
    out = Path(out)
    cal, info = fit_calibration(presses, sensor, simulator, train, settings, on_step)
    cal.save(out)
    rows, sp = calibration_rows(presses, sensor, cal, info, simulator, test, str(out))
    size = f"{sensor.width}x{sensor.height}"
    intro = [f"Presses: {presses.folder}.", *fit_summary(info, settings, size)]
    record = report.write_report(
        out,
        f"Realism of sensor {sensor.name!r} on held-out presses {list(test)}",
        intro,
        rows,
        presses,
        sp,
        grid_presses=grid_presses,
        region_scale=settings.region_scale,
        extra={"fit": info},
    )
    return record
