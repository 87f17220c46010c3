"""The report's judgements: whether the paper's qualitative claims hold in our numbers (``checks``), whether our
method reaches the paper's own figures (``against_paper``), and the one-paragraph verdict (``verdict``)."""

from __future__ import annotations

import math
import re

from tnf.eval.aggregate import Stat, TableData
from tnf.eval.paper import PAPER
from tnf.eval.scoring import BG
from tnf.eval.tables import (
    PRIMARY,
    TABLES,
    TEST_SET_NAMES,
    fmt_stat,
    ordered_methods,
)


def checks(table: str, data: TableData) -> list[tuple[str, str, str]]:
    """The paper's qualitative claims tested on our numbers: (claim, verdict, detail).

    Verdict ``holds`` or ``FAILS``, with `` (within noise)`` when the gap is no larger than the combined standard
    error over seeds. Claims whose rows are missing are left out.
    """
    out: list[tuple[str, str, str]] = []

    def compare(claim: str, a: Stat | None, b: Stat | None, higher_better: bool, kind: str) -> None:
        if a is None or b is None:
            return
        better = a.mean > b.mean if higher_better else a.mean < b.mean
        noise = math.hypot(a.se, b.se)
        close = abs(a.mean - b.mean) <= noise
        verdict = (
            ("holds (within noise)" if close else "holds") if better else ("FAILS (within noise)" if close else "FAILS")
        )
        out.append((claim, verdict, f"{fmt_stat(a, kind)} vs {fmt_stat(b, kind)}"))

    def img(ts: str, method: str, metric: str) -> Stat | None:
        return data.image.get((ts, method), {}).get(metric)

    test_sets = sorted({k[0] for k in data.image} - {"all"}, key=lambda t: (t != "novel_view", t))
    others = [m for m in ordered_methods(table, data) if m != PRIMARY]
    baselines = [m for m in others if not m.startswith(PRIMARY)]  # T-N+ is a variant of ours, not a baseline
    for ts in test_sets:
        name = TEST_SET_NAMES.get(ts, ts).lower()
        for b in baselines:
            compare(f"{PRIMARY} SSIM > {b} SSIM ({name})", img(ts, PRIMARY, "ssim"), img(ts, b, "ssim"), True, "ssim")
            compare(f"{PRIMARY} MSE < {b} MSE ({name})", img(ts, PRIMARY, "mse"), img(ts, b, "mse"), False, "mse")
        compare(f"{PRIMARY} SSIM > BG SSIM ({name})", img(ts, PRIMARY, "ssim"), img(ts, BG, "ssim"), True, "ssim")
        compare(f"{PRIMARY} MSE < BG MSE ({name})", img(ts, PRIMARY, "mse"), img(ts, BG, "mse"), False, "mse")
        if f"{PRIMARY}+" in others and ts == "novel_object":
            compare(
                f"{PRIMARY}+ SSIM > {PRIMARY} SSIM ({name})",
                img(ts, f"{PRIMARY}+", "ssim"),
                img(ts, PRIMARY, "ssim"),
                True,
                "ssim",
            )
    acc = data.accuracy
    compare(f"Sim + {PRIMARY} accuracy > Sim", acc.get(f"Sim + {PRIMARY}"), acc.get("Sim"), True, "acc")
    for b in baselines:
        compare(
            f"Sim + {PRIMARY} accuracy > Sim + {b}", acc.get(f"Sim + {PRIMARY}"), acc.get(f"Sim + {b}"), True, "acc"
        )
    return out


def against_paper(table: str, data: TableData) -> list[tuple[str, str, str]]:
    """Our method's figures (T-N and its variants) against the paper's own: (figure, verdict, ours vs paper).

    Verdict ``reaches``, ``short, within noise`` when the shortfall is within the combined standard error, or
    ``FALLS SHORT``. The classification figure is the gain of ``Sim + <method>`` over ``Sim``.
    """
    paper = PAPER.get(table, {})
    ours = [m for m in ordered_methods(table, data) if m.startswith(PRIMARY)]
    out: list[tuple[str, str, str]] = []

    def compare(what: str, a: Stat | None, b: tuple[float, float] | None, higher_better: bool, kind: str) -> None:
        if a is None or b is None:
            return
        ahead = a.mean >= b[0] if higher_better else a.mean <= b[0]
        short = "short, within noise" if abs(a.mean - b[0]) <= math.hypot(a.se, b[1]) else "FALLS SHORT"
        out.append((what, "reaches" if ahead else short, f"{fmt_stat(a, kind)} vs {fmt_stat(b, kind)}"))

    image = paper.get("image", {})
    for ts, method in sorted(image, key=lambda k: (k[0] != "novel_view", k[0], k[1])):
        if method in ours:
            name = TEST_SET_NAMES.get(ts, ts).lower()
            for metric, higher_better in (("ssim", True), ("mse", False)):
                a, b = data.image.get((ts, method), {}).get(metric), image[(ts, method)].get(metric)
                compare(f"{method} {metric.upper()} ({name})", a, b, higher_better, metric)
    acc, paper_acc = data.accuracy, paper.get("accuracy", {})
    for m in ours:
        a, a0, b, b0 = acc.get(f"Sim + {m}"), acc.get("Sim"), paper_acc.get(f"Sim + {m}"), paper_acc.get("Sim")
        if a is not None and a0 is not None and b is not None and b0 is not None:
            gain = Stat(a.mean - a0.mean, math.hypot(a.se, a0.se), min(a.n, a0.n))
            compare(f"Sim + {m} gain over Sim (points)", gain, (b[0] - b0[0], math.hypot(b[1], b0[1])), True, "acc")
    return out


def _plain(claim: str) -> str:
    """A check's claim in words: ``T-N SSIM > BG SSIM (novel view)`` -> ``T-N above BG in SSIM on novel views``."""
    m = re.fullmatch(r"(\S+) (SSIM|MSE) ([<>]) (\S+) (?:SSIM|MSE) \((.+)\)", claim)
    if not m:
        return claim.replace(" > ", " above ").replace(" < ", " below ")
    a, metric, op, b, where = m.groups()
    return f"{a} {'above' if op == '>' else 'below'} {b} in {metric} on {where}s"


def verdict(tables: dict[str, TableData], next_step: str | None = None) -> str:
    """The report's first paragraph, in plain words: whether the paper's claims that the run checks hold, how
    the primary method's SSIM compares with the paper's, then ``next_step`` (the experiment's own words)."""
    parts: list[str] = []
    for table in sorted(tables, key=lambda t: (t not in TABLES, t)):
        data = tables[table]
        cks = checks(table, data)
        if not cks:
            continue
        label = f" (Table {TABLES.get(table, (table,))[0]})" if len(tables) > 1 else ""
        seeds = len({r["seed"] for r in data.runs if r["method"] == PRIMARY})
        on = f"on {seeds} seed{'s' if seeds != 1 else ''}" if seeds else "so far"
        failed = [
            (c, d + (", within the spread between seeds" if v.endswith("(within noise)") else ""))
            for c, v, d in cks
            if v.startswith("FAILS")
        ]
        noisy = sum(v == "holds (within noise)" for _, v, _ in cks)
        if failed:
            listed = "; ".join(f"{_plain(c)} ({d.replace(' vs ', ' against ')})" for c, d in failed)
            held = f"{len(cks) - len(failed)} of {len(cks)}"
            parts.append(f"**{held} claims of the paper hold{label} {on}; these do not: {listed}.**")
        else:
            close = f", {noisy} of them by less than the spread between seeds" if noisy else ""
            count = f"{len(cks)} of {len(cks)}, {on}{close}"
            parts.append(f"**Every claim of the paper that this run checks holds{label} ({count}).**")
        test_sets = sorted({k[0] for k in data.image} - {"all"}, key=lambda t: (t != "novel_view", t))
        image_failed = any("accuracy" not in c for c, _ in failed)
        baselines = [m for m in ordered_methods(table, data) if not m.startswith(PRIMARY)]
        compared = [
            t for t in test_sets if (t, PRIMARY) in data.image and any((t, m) in data.image for m in [BG, *baselines])
        ]
        if compared and not image_failed:
            rivals = ["the background image"] + baselines
            where = " and ".join(TEST_SET_NAMES.get(t, t).lower() + "s" for t in compared)
            parts.append(
                f"{PRIMARY}'s generated touches are closer to the true ones than {', '.join(rivals)} on {where}, "
                "in SSIM and in MSE."
            )
        sim, with_primary = data.accuracy.get("Sim"), data.accuracy.get(f"Sim + {PRIMARY}")
        if sim and with_primary and with_primary.mean > sim.mean:  # a failed claim is named above
            parts.append(
                f"Added to the simulator's touches, {PRIMARY}'s touches train a better object classifier "
                f"({fmt_stat(with_primary, 'acc')} % against {fmt_stat(sim, 'acc')} %)."
            )
        paper = PAPER.get(table, {}).get("image", {})
        ours = [
            (t, data.image[(t, PRIMARY)]["ssim"], paper[(t, PRIMARY)]["ssim"])
            for t in test_sets
            if "ssim" in data.image.get((t, PRIMARY), {}) and (t, PRIMARY) in paper
        ]
        if ours:
            names = " / ".join(TEST_SET_NAMES.get(t, t).lower() for t, _, _ in ours)
            here = " / ".join(fmt_stat(o, "ssim").split(" ")[0] for _, o, _ in ours)
            theirs = " / ".join(fmt_stat(p, "ssim").split(" ")[0] for _, _, p in ours)
            level = (
                "below"
                if all(o.mean < p[0] for _, o, p in ours)
                else "at or above"
                if all(o.mean >= p[0] for _, o, p in ours)
                else "around"
            )
            parts.append(f"{PRIMARY}'s SSIM here ({names}: {here}) is {level} the paper's ({theirs}).")
    if not parts:
        parts.append("**No claim of the paper can be checked yet**: the rows it compares are missing.")
    if next_step and next_step.strip():
        parts.append(next_step.strip())
    return " ".join(parts)
