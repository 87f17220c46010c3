"""The realism report: every way of making a tactile image of the held-out presses, scored against the real frames.

A row is one source of images of the held-out presses (the no-contact frame, a simulator, a generator), at any
size. Each row is scored twice against the real frames:

* **native crop**: at the recording's own size (rows upsampled bilinearly when smaller), on a square of side
  ``crop_scale`` x the annotated contact radius around the annotated centre: SSIM with scikit-image's defaults,
  MSE, and the sharpness ratio (mean Sobel gradient magnitude, row over real), :func:`tnf.real.realism.crop_score`;
* **contact region**: at the sensor's size (rows resized bilinearly, as the real frames are), on the disk of
  ``region_scale`` x the contact radius, with tnf's SSIM, :func:`tnf.real.realism.score`.

:func:`write_report` writes ``realism.md`` (the table and the per-press figures), ``realism.json`` and
``realism.png`` (real | each row, cropped around the contact at the recording's size).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tnf.artifacts import write_json
from tnf.real import realism
from tnf.real.presses import PressSet, SensorPresses

ALL_METRICS = realism.CROP_METRICS + realism.METRICS


@dataclass
class Row:
    """One source of images of the held-out presses."""

    name: str
    images: np.ndarray
    """``[N, h, w, 3]`` uint8, one per held-out press, at any size of the recording's aspect ratio."""
    seconds: float | None = None
    """Seconds per frame on this machine, where measured."""


def resize(images: np.ndarray, width: int, height: int) -> np.ndarray:
    """``[N, h, w, 3]`` uint8 resized to ``width x height`` with PIL's bilinear filter (as frames are loaded)."""
    return realism.upsample(images, width, height)


def score_rows(
    rows: Sequence[Row], presses: PressSet, sp: SensorPresses, crop_scale: float = 4.0, region_scale: float = 1.5
) -> dict[str, dict[str, list[float]]]:
    """``{row: {metric: [N]}}`` for the native crop (:data:`realism.CROP_METRICS`) and the contact region
    (:data:`realism.METRICS`); ``sp`` holds the same presses at the sensor's size."""
    h, w = sp.background.shape[:2]
    region = realism.regions(sp, region_scale)
    out = {}
    for row in rows:
        if len(row.images) != len(sp.indices):
            raise ValueError(f"row {row.name!r} has {len(row.images)} images for {len(sp.indices)} presses")
        native = realism.native_score(row.images, presses, sp.indices, crop_scale)
        small = realism.score(resize(row.images, w, h), sp.frames, region)
        out[row.name] = {**native, **small}
    return out


def mean_scores(scores: Mapping[str, Mapping[str, list[float]]]) -> dict[str, dict[str, float]]:
    """``{row: {metric: mean over presses}}`` of :func:`score_rows`' output."""
    return {n: {m: float(np.mean(v[m])) for m in ALL_METRICS} for n, v in scores.items()}


def table(means: Mapping[str, Mapping[str, float]], seconds: Mapping[str, float | None] | None = None) -> str:
    """Markdown: one line per row, the native crop's three figures, the contact region's two, and milliseconds
    per frame where ``seconds`` (per frame) gives them."""
    lines = [
        "| | crop SSIM | crop MSE | sharpness | region SSIM | region MSE | ms per frame |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, m in means.items():
        ms = (seconds or {}).get(name)
        cells = [
            f"{m['ssim_crop']:.3f}",
            f"{m['mse_crop']:.0f}",
            f"{m['sharpness']:.2f}",
            f"{m['ssim_region']:.3f}",
            f"{m['mse_region']:.0f}",
            f"{1e3 * ms:.1f}" if ms is not None else "",
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def per_press_table(scores: Mapping[str, Mapping[str, list[float]]], indices: Sequence[int]) -> str:
    """Markdown: crop SSIM / MSE of each row on each press."""
    names = list(scores)
    lines = ["| press | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for k, i in enumerate(indices):
        cells = [f"{scores[n]['ssim_crop'][k]:.3f} / {scores[n]['mse_crop'][k]:.0f}" for n in names]
        lines.append(f"| {i} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(
    out: str | Path,
    title: str,
    intro: Sequence[str],
    rows: Sequence[Row],
    presses: PressSet,
    sp: SensorPresses,
    grid_rows: Sequence[str] | None = None,
    grid_presses: int = 4,
    crop_scale: float = 4.0,
    region_scale: float = 1.5,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Score ``rows`` on the held-out presses ``sp.indices`` and write ``realism.md``, ``realism.json`` and
    ``realism.png`` into ``out``. ``grid_rows`` names the rows shown beside the real frames (default: all).

    Returns the record written to ``realism.json``: per press, means, seconds per frame, and ``extra``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scores = score_rows(rows, presses, sp, crop_scale, region_scale)
    means = mean_scores(scores)
    seconds = {r.name: r.seconds for r in rows}
    shown = list(grid_rows) if grid_rows is not None else [r.name for r in rows]
    k = min(grid_presses, len(sp.indices))
    real = np.stack([presses.frame(i) for i in sp.indices[:k]])
    native = {r.name: resize(r.images[:k], presses.width, presses.height) for r in rows if r.name in shown}
    centers = np.array([presses.presses[i].center for i in sp.indices[:k]], dtype=float)
    side = int(round(crop_scale * max(presses.contact_radius_px(i) for i in sp.indices[:k]) * 1.25))
    realism.grid(real, {n: native[n] for n in shown}, centers, out / "realism.png", crop=side, zoom=1, diffs=False)
    record = {
        "test": list(sp.indices),
        "per_press": scores,
        "mean": means,
        "seconds_per_frame": seconds,
        "presses": str(presses.folder),
        "crop_scale": crop_scale,
        "region_scale": region_scale,
        **(dict(extra) if extra else {}),
    }
    write_json(out / "realism.json", record)
    lines = [
        f"# {title}",
        "",
        *intro,
        "",
        f"Native crop: at the recording's {presses.width}x{presses.height}, a square of side {crop_scale:g} x the "
        "annotated contact radius around the annotated centre; SSIM with scikit-image's defaults; sharpness is "
        "the mean Sobel gradient magnitude, the row's over the real frame's. Contact region: at the sensor's "
        f"{sp.background.shape[1]}x{sp.background.shape[0]}, {region_scale:g} x the contact radius, tnf's SSIM.",
        "",
        table(means, seconds),
        "",
        "Native crop SSIM / MSE per held-out press:",
        "",
        per_press_table(scores, sp.indices),
        "",
        f"![real | {' | '.join(shown)}](realism.png)",
        "",
    ]
    (out / "realism.md").write_text("\n".join(lines))
    return record
