"""The report's tables: their names and test sets, the order of methods, and rows of formatted means with
standard errors beside the paper's figures (``image_rows``, ``accuracy_rows``; CSV bytes with ``csv_bytes``)."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from typing import Any

from tnf.eval.aggregate import Stat, TableData
from tnf.eval.paper import PAPER
from tnf.eval.scoring import BG

TABLES = {"main": ("1", "Simulated tactile images (the paper's: Digit)"), "transfer": ("2", "Transfer to a new sensor")}


TEST_SET_NAMES = {
    "novel_view": "Novel view",
    "novel_object": "Novel object",
    "all": "All test sets",
    "val": "Validation",
    "train": "Training",
}


# The paper's method order per table; methods it does not have follow in the order first seen.
METHOD_ORDER = {"main": ["T-N", "Lee", "Cycle"], "transfer": ["T-N", "T-N+", "FS"]}


PRIMARY = "T-N"


def _fmt(x: float, kind: str) -> str:
    if kind == "ssim":
        return f"{x:.3f}"
    if kind == "acc":
        return f"{x:.1f}"
    return f"{x:.1f}" if abs(x) < 100 else f"{x:.0f}"


def fmt_stat(st: Stat | tuple[float, float] | None, kind: str) -> str:
    """'mean ± se', the value alone for one seed (no spread to state), or '-' when missing."""
    if st is None:
        return "-"
    if isinstance(st, Stat) and st.n == 1:
        return _fmt(st.mean, kind)
    m, se = (st.mean, st.se) if isinstance(st, Stat) else st
    return f"{_fmt(m, kind)} ± {_fmt(se, kind)}"


def ordered_methods(table: str, data: TableData) -> list[str]:
    """The methods of ``data`` in the table's order (``METHOD_ORDER``), then the others as they came."""
    order = [m for m in METHOD_ORDER.get(table, []) if m in data.methods]
    return order + [m for m in data.methods if m not in order]


def _row_methods(table: str, data: TableData) -> list[str]:
    """The paper's methods of this table (so its figures show even without a run of ours), then ours."""
    paper = METHOD_ORDER.get(table, [])
    return paper + [m for m in ordered_methods(table, data) if m not in paper]


def image_rows(table: str, data: TableData) -> list[dict[str, Any]]:
    """Rows of table a: per test set each method then BG, last the pooled BG row; ours and the paper's."""
    paper = PAPER.get(table, {}).get("image", {})
    keys = set(data.image) | set(paper)
    test_sets = [t for t in ("novel_view", "novel_object") if any(k[0] == t for k in keys)]
    test_sets += sorted({k[0] for k in keys} - set(test_sets) - {"all"})
    rows = []
    for ts in test_sets:
        for method in [*_row_methods(table, data), BG]:
            if (ts, method) in data.image or (ts, method) in paper:
                rows.append(_image_row(ts, method, data.image.get((ts, method), {}), paper.get((ts, method), {})))
    if ("all", BG) in data.image or ("all", BG) in paper:
        rows.append(_image_row("all", BG, data.image.get(("all", BG), {}), paper.get(("all", BG), {})))
    return rows


def _image_row(ts: str, method: str, ours: dict[str, Stat], paper: dict[str, tuple[float, float]]) -> dict:
    return {"test_set": ts, "method": method, "ours": ours, "paper": paper}


def accuracy_rows(table: str, data: TableData) -> list[dict[str, Any]]:
    paper = PAPER.get(table, {}).get("accuracy", {})
    methods = _row_methods(table, data)
    names = ["Sim", *[f"Sim + {m}" for m in methods], *[f"{m} only" for m in methods]]
    names = [n for n in names if n in data.accuracy or n in paper]
    names += [n for n in data.accuracy if n not in names]
    return [{"row": n, "ours": data.accuracy.get(n), "paper": paper.get(n)} for n in names]


def csv_bytes(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> bytes:
    """A CSV file's bytes: ``header``, then ``rows`` (floats to 6 significant digits, None as an empty cell)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in rows:
        w.writerow(["" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for v in r])
    return buf.getvalue().encode()


def paper_cells(p: tuple[float, float] | None) -> tuple[float | None, float | None]:
    """The cells of a paper's figure ``(value, spread)``: two empty cells when the paper gives none."""
    return (None, None) if p is None else p


def stat_cells(st: Stat | None) -> list[Any]:
    """The cells of one of our figures: mean, standard error and number of seeds (three empty cells if missing)."""
    return [None, None, None] if st is None else [st.mean, st.se, st.n]
