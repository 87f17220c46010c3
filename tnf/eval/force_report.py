"""The report's section on evaluation by force (``tnf.eval.force``): runs whose results hold ``force``.

Per test split, the mean ± standard error over seeds of SSIM and MSE per force band, the contact-area
correlation with the simulator and the share of poses whose area grows with force; then the targets of
docs/force.md and each run's force-sweep figure.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tnf.sim.forces import BANDS

TARGETS = {"interpolation_gap": 0.01, "area_r": 0.95, "monotonic": 0.95}
"""docs/force.md's targets: interpolation-band SSIM within 0.01 of the training range's, contact-area r >= 0.95
on novel views, area growing with force for >= 95 % of poses."""


def _stat(values: Sequence[float | None]) -> tuple[float, float, int] | None:
    v = [float(x) for x in values if x is not None]
    if not v:
        return None
    se = float(np.std(v, ddof=1) / np.sqrt(len(v))) if len(v) > 1 else 0.0
    return float(np.mean(v)), se, len(v)


def _fmt(st: tuple[float, float, int] | None, digits: int) -> str:
    if st is None:
        return "-"
    m, se, n = st
    return f"{m:.{digits}f}" if n == 1 else f"{m:.{digits}f} ± {se:.{digits}f}"


def force_section(runs: Sequence[dict[str, Any]], folder: Path) -> list[str]:
    """Markdown lines of the section (empty when no run has an evaluation by force)."""
    runs = [r for r in runs if r.get("force")]
    if not runs:
        return []
    lines = ["## Evaluation by force", "", *_band_table_head(runs[0]["force"])]
    methods = sorted({r["method"] for r in runs})
    splits = [s for s in ("novel_view", "novel_object") if any(s in r["force"] for r in runs)]
    verdicts = []
    for split in splits:
        for m in methods:
            mine = [r["force"][split] for r in runs if r["method"] == m and split in r["force"]]
            rows, ssim_by = _band_rows(split, m, mine)
            lines += rows
            verdicts += _verdicts(split, m, mine, ssim_by)
    verdicts += _simulator_verdicts(runs, methods)
    lines += ["", "| Test set | Method | Target | Verdict | Ours |", "|---|---|---|---|---|", *verdicts, ""]
    lines += _figures(runs, methods, folder)
    return lines


def _band_table_head(force: dict[str, Any]) -> list[str]:
    """The section's opening paragraph (the force plan of a run's ``force`` results, newtons, and the contact
    area's threshold) and the head of the table of SSIM and MSE per force band."""
    plan = force["plan"]
    return [
        f"Training range {plan['min']:g}-{plan['max']:g} N ({plan['dist']}); held out: interpolation band "
        f"{plan['interpolation'][0]:g}-{plan['interpolation'][1]:g} N, extrapolation band "
        f"{plan['extrapolation'][0]:g}-{plan['extrapolation'][1]:g} N. Each test touch is generated at its own "
        f"simulated force. Contact area: pixels over {force['area_threshold']:g} levels from the "
        "background (docs/force.md). Mean ± standard error over seeds.",
        "",
        "| Test set | Method | Band | SSIM ↑ | MSE ↓ | touches | seeds |",
        "|---|---|---|---|---|---|---|",
    ]


def _band_rows(
    split: str, method: str, mine: Sequence[dict[str, Any]]
) -> tuple[list[str], dict[str, tuple[float, float, int] | None]]:
    """The table rows of one test split and method, one per force band (``mine``: each seed's ``score_split``
    results); returns them and the SSIM (mean, standard error, seeds) of each band."""
    lines = []
    ssim_by = {}
    for band in (*BANDS, "adjacent"):
        rows = [x["bands"].get(band, {}) for x in mine]
        s, e = _stat([b.get("ssim") for b in rows]), _stat([b.get("mse") for b in rows])
        ssim_by[band] = s
        n = rows[0].get("n", 0) if rows else 0
        lines.append(f"| {split} | {method} | {band} | {_fmt(s, 4)} | {_fmt(e, 1)} | {n} | {s[2] if s else 0} |")
    return lines, ssim_by


def _verdicts(
    split: str, m: str, mine: Sequence[dict[str, Any]], ssim_by: dict[str, tuple[float, float, int] | None]
) -> list[str]:
    """Rows of the verdict table for one test split and method: each of ``TARGETS`` met or missed, and the bands
    without a target (``ssim_by``: the SSIM of each band, ``mine``: each seed's results)."""
    verdicts = []
    if ssim_by["adjacent"] and ssim_by["interpolation"]:
        gap = ssim_by["adjacent"][0] - ssim_by["interpolation"][0]
        verdicts.append(
            f"| {split} | {m} | interpolation SSIM against adjacent training forces (no target) | - | gap {gap:.4f} |"
        )
    r_ = _stat([x["area"]["r"] for x in mine])
    mono = _stat([x["monotonic"]["share"] for x in mine])
    if ssim_by["train"] and ssim_by["interpolation"]:
        gap = ssim_by["train"][0] - ssim_by["interpolation"][0]
        ok = "meets" if gap <= TARGETS["interpolation_gap"] else "misses"
        verdicts.append(
            f"| {split} | {m} | interpolation SSIM within {TARGETS['interpolation_gap']} of training range | "
            f"{ok} | gap {gap:.4f} |"
        )
    if r_:
        ok = "meets" if r_[0] >= TARGETS["area_r"] else "misses"
        verdicts.append(f"| {split} | {m} | contact area r >= {TARGETS['area_r']} | {ok} | r {_fmt(r_, 3)} |")
    elif mine:  # no seed's areas vary (e.g. a generator that draws no contact anywhere): no correlation
        verdicts.append(
            f"| {split} | {m} | contact area r >= {TARGETS['area_r']} | misses | undefined: the areas do not vary |"
        )
    if mono:
        ok = "meets" if mono[0] >= TARGETS["monotonic"] else "misses"
        verdicts.append(
            f"| {split} | {m} | area grows with force for >= {TARGETS['monotonic']:.0%} of poses | {ok} | "
            f"{_fmt(mono, 3)} |"
        )
    if ssim_by["extrapolation"]:
        verdicts.append(
            f"| {split} | {m} | extrapolation band (no target) | - | SSIM {_fmt(ssim_by['extrapolation'], 4)} |"
        )
    return verdicts


def _simulator_verdicts(runs: Sequence[dict[str, Any]], methods: Sequence[str]) -> list[str]:
    """Rows of the verdict table: how often the simulator's own contact area grows with force (the reference
    that the generator's growth is measured against), per method's runs."""
    verdicts = []
    for m in methods:
        ref = [r["force"].get("simulator_monotonic") for r in runs if r["method"] == m]
        st = _stat([x["share"] for x in ref if x])
        if st:
            n = next(x["n"] for x in ref if x)
            verdicts.append(
                f"| {runs[0]['force'].get('figure', {}).get('split', '-')} | simulator | area grows with force "
                f"(reference, {n} poses pressed again) | - | {_fmt(st, 3)} |"
            )
    return verdicts


def _figures(runs: Sequence[dict[str, Any]], methods: Sequence[str], folder: Path) -> list[str]:
    """Markdown lines of each method's force sweep figure (its first seed's), linked relative to ``folder``."""
    import os

    lines = []
    for m in methods:
        first = sorted((r for r in runs if r["method"] == m and r.get("force_figure")), key=lambda r: r["seed"])
        if first and "_path" in first[0]:
            fig = Path(first[0]["_path"]).parent / first[0]["force_figure"]
            info = first[0]["force"].get("figure", {})
            caption = (
                f"{m}, {info.get('object', '?')} touch {info.get('touch', '?')} (seed {first[0]['seed']}): the "
                "simulator pressed again (top) and the generator (bottom) from light to hard"
            )
            lines += [f"**{caption}**", "", f"![{caption}]({os.path.relpath(fig.absolute(), folder.absolute())})", ""]
    return lines
