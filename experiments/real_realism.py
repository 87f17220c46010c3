"""Realism against real GelSight Mini frames: tnf uncalibrated, tnf calibrated and Taxim, on the same held-out presses.

Fits tnf's calibration on presses 0-15 of the GelSight Mini recording that the ``taxim`` package ships, then
renders presses 16-23 with tnf (its hand-set optics, and calibrated) and with Taxim (its JAX backend, its own
calibration of this sensor, with and without its shadows), scores all three against the real frames with the same code
(``tnf.real.realism.score``, at tnf's 320x240), and times each simulator per frame on this machine. Taxim renders
at its native 640x480; its frames are resized to 320x240 as the real ones are. For a like-for-like time, tnf is
also timed at 640x480 (the same table, blur doubled, over the full-size background).

Each press is placed at its annotated centre. Taxim presses to the depth at which the ball crosses the gel in
the annotated circle, as its calibration defines it; tnf to that depth times its fitted ``depth_scale``.

    python experiments/real_realism.py --out results/real/gelsight_mini      # ~2 min on 2 CPU cores

Prints the table; writes ``report.md`` and ``realism.png`` (real | tnf uncalibrated | tnf calibrated | Taxim |
differences) into ``--out``, and the per-press figures to ``--raw`` (kept out of git).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np


def taxim_frames(presses, indices, with_shadow: bool = True) -> tuple[np.ndarray, float]:
    """Taxim's frames ``[N, 480, 640, 3]`` uint8 of the presses, and its warm seconds per frame."""
    from taxim import CALIB_GELSIGHT_MINI, Taxim

    sim = Taxim(calib_folder=CALIB_GELSIGHT_MINI, backend="jax")
    h, w, pix, r = presses.height, presses.width, presses.mm_per_pixel, presses.radius_mm
    rows, cols = np.mgrid[:h, :w]

    def height_map(i: int) -> tuple[np.ndarray, float]:
        p = presses.presses[i]
        d2 = ((cols - p.center[0]) ** 2 + (rows - p.center[1]) ** 2) * pix**2
        z = np.where(d2 < r * r, r - np.sqrt(np.maximum(r * r - d2, 0.0)), 10.0 * r)  # mm above the lowest point
        return z.astype(np.float32), float(p.depth_mm)

    z, d = height_map(indices[0])
    np.asarray(sim.render(z, with_shadow=with_shadow, press_depth=d))  # compile
    out, spent = [], 0.0
    for i in indices:
        z, d = height_map(i)
        t0 = time.perf_counter()
        img = np.asarray(sim.render(z, with_shadow=with_shadow, press_depth=d))
        spent += time.perf_counter() - t0
        out.append(np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8))
    return np.stack(out), spent / len(indices)


def resize(frames: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize ``[N, H, W, 3]`` uint8 as ``tnf.sensors.load_background`` resizes image files (PIL bilinear)."""
    from PIL import Image

    return np.stack([np.asarray(Image.fromarray(f).resize((width, height), Image.Resampling.BILINEAR)) for f in frames])


def tnf_full_size_seconds(sensor, cal, presses, indices, depth_scale: float) -> float:
    """tnf's calibrated simulator per frame at the recording's 640x480 (same table, blur in full-size pixels)."""
    from tnf.real.calibrate import at_sensor_size
    from tnf.real.realism import render
    from tnf.sensors.base import load_background

    k = presses.width / sensor.width
    big = type(sensor)(
        dataclasses.replace(sensor.cfg, width=presses.width, height=presses.height, calibration=None, noise_std=0.0)
    )
    big_cal = dataclasses.replace(
        cal,
        blur_sigma=cal.blur_sigma * k,
        background=load_background(presses.background_path, presses.width, presses.height),
    )
    big = big.calibrated(big_cal, "full-size timing")
    sp = at_sensor_size(presses, big, indices)
    return render(big, {"name": "warp_gel"}, sp, presses.radius_mm * 1e-3, depth_scale)[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="results/real/gelsight_mini", help="report.md and realism.png go here")
    ap.add_argument("--raw", default=None, help="per-press JSON and the calibration (default: a temporary folder)")
    ap.add_argument("--train", default="0-15")
    ap.add_argument("--test", default="16-23")
    args = ap.parse_args()

    from tnf.real import realism
    from tnf.real.calibrate import FitSettings, at_sensor_size, fit_calibration
    from tnf.real.presses import import_taxim
    from tnf.registry import SENSORS
    from tnf.runtime import environment

    def span(text: str) -> list[int]:
        a, b = (int(x) for x in text.split("-"))
        return list(range(a, b + 1))

    train, test = span(args.train), span(args.test)
    raw = Path(args.raw or tempfile.mkdtemp(prefix="tnf-realism-"))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    presses = import_taxim("gelsight_mini", raw / "presses")
    sensor = SENSORS.build("gelsight_mini")
    settings = FitSettings()
    t0 = time.perf_counter()
    cal, info = fit_calibration(presses, sensor, {"name": "warp_gel"}, train, settings)
    fit_s = time.perf_counter() - t0
    cal.save(raw / "calibration")

    plain = type(sensor)(dataclasses.replace(sensor.cfg, background_image=str(presses.background_path)))
    calibrated = plain.calibrated(cal, str(raw / "calibration"))
    sp = at_sensor_size(presses, plain, test)
    region = realism.regions(sp, settings.region_scale)
    radius = presses.radius_mm * 1e-3
    images, seconds = {}, {}
    images["tnf uncalibrated"], seconds["tnf uncalibrated"] = realism.render(plain, {"name": "warp_gel"}, sp, radius)
    images["tnf calibrated"], seconds["tnf calibrated"] = realism.render(
        calibrated, {"name": "warp_gel"}, sp, radius, info["depth_scale"]
    )
    taxim_full, taxim_s = taxim_frames(presses, test)
    images["Taxim"] = resize(taxim_full, sensor.width, sensor.height)
    seconds["Taxim"] = taxim_s
    plain_full, seconds["Taxim, no shadows"] = taxim_frames(presses, test, with_shadow=False)
    images["Taxim, no shadows"] = resize(plain_full, sensor.width, sensor.height)
    full_s = tnf_full_size_seconds(sensor, cal, presses, test, info["depth_scale"])
    scores = {n: realism.score(v, sp.frames, region) for n, v in images.items()}
    means = realism.summary(scores)
    shown = ("tnf uncalibrated", "tnf calibrated", "Taxim")
    realism.grid(sp.frames[:4], {n: images[n][:4] for n in shown}, sp.centers[:4], out / "realism.png")
    (raw / "realism.json").write_text(json.dumps({"per_press": scores, "mean": means, "fit": info}, indent=1))

    env = environment("cpu")
    wins = [
        m
        for m, better in (("ssim_region", max), ("mse_region", min))
        if better(means["tnf calibrated"][m], means["Taxim"][m]) == means["tnf calibrated"][m]
    ]
    per_press = [
        "| press | " + " | ".join(f"{n} SSIM / MSE" for n in images) + " |",
        "|---|" + "---|" * len(images),
    ]
    for k, i in enumerate(test):
        cells = [f"{scores[n]['ssim_region'][k]:.3f} / {scores[n]['mse_region'][k]:.0f}" for n in images]
        per_press.append(f"| {i} | " + " | ".join(cells) + " |")
    lines = [
        "# Realism against real GelSight Mini frames",
        "",
        f"Held-out presses {test[0]}-{test[-1]} of the GelSight Mini recording in the `taxim` package; "
        "tnf's calibration "
        f"fitted on presses {train[0]}-{train[-1]} in {fit_s:.1f} s on this machine's CPU. Contact region: "
        f"{settings.region_scale:g} x each press's annotated contact radius, at 320x240.",
        "",
        realism.table(means, seconds),
        "",
        f"tnf calibrated at Taxim's 640x480: {1e3 * full_s:.1f} ms per frame "
        f"({taxim_s / full_s:.1f}x faster than Taxim's {1e3 * taxim_s:.0f} ms).",
        "",
        "Against Taxim (with its shadows, its default) on the contact region: tnf calibrated is "
        + (
            "ahead in both SSIM and MSE."
            if len(wins) == 2
            else f"ahead in {wins[0].split('_')[0].upper()} only."
            if wins
            else "behind in SSIM and in MSE."
        ),
        "",
        f"Fit: fall-off {info['falloff']:g} x thickness, depth x{info['depth_scale']:g}, "
        f"blur {info['blur_sigma']:g} px, "
        f"table {settings.table_size}x{settings.table_size} over slopes +-{settings.max_slope:g}; "
        f"measured frame noise {info['frame_noise_std']:.2f} (8-bit).",
        "",
        "Contact-region SSIM / MSE per held-out press:",
        "",
        *per_press,
        "",
        "![real | tnf uncalibrated | tnf calibrated | Taxim | differences](realism.png)",
        "",
        f"Machine: {env['accelerator']} ({env['cpu_cores']} cores), Python "
        f"{platform.python_version()}, warp {env['warp']}, tnf commit {env['commit']}, Taxim's JAX backend. Reproduce: "
        "`python experiments/real_realism.py --out results/real/gelsight_mini`.",
        "",
    ]
    (out / "report.md").write_text("\n".join(lines))
    print(realism.table(means, seconds))
    print(f"tnf calibrated at 640x480: {1e3 * full_s:.1f} ms/frame; report: {out / 'report.md'}")


if __name__ == "__main__":
    main()
