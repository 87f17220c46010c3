"""Every fitted scene's figures in one table: held-out PSNR and SSIM, median depth error, fit time, peak memory.

    python experiments/scene_table.py tnf-data [--scene hashgrid] [--source builtin] [--csv scenes.csv]

Reads ``<data_root>/scenes/<scene>/<source>/<object>/metrics.json`` (written by ``tnf fit-scene``), prints one
line per object and a summary against the quality bars: 30 dB held-out PSNR and 1 % median depth error (of the
object's size). ``experiments/paper_runs.sh digit-scenes`` runs it after fitting sim_digit's 27 objects.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PSNR_BAR = 30.0
DEPTH_BAR = 1.0  # percent of the object's size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_root")
    ap.add_argument("--scene", default="hashgrid")
    ap.add_argument("--source", default="builtin")
    ap.add_argument("--csv", help="also write the table here")
    a = ap.parse_args()

    from tnf.artifacts import read_json
    from tnf.errors import TnfError

    folder = Path(a.data_root) / "scenes" / a.scene / a.source
    files = sorted(folder.glob("*/metrics.json"))
    if not files:
        raise TnfError(f"no fitted scenes under {folder}: run `tnf fit-scene` first")
    rows = []
    for f in files:
        m = read_json(f, "scene metrics")
        missing = [k for k in ("steps", "psnr", "ssim", "train_seconds") if k not in m]
        if missing:
            raise TnfError(f"scene metrics {f} lack {', '.join(missing)}; fit the scene again with `tnf fit-scene`")
        depth = m.get("depth_error_median_rel")
        rows.append(
            {
                "object": f.parent.name,
                "steps": m["steps"],
                "psnr_db": round(m["psnr"], 2),
                "ssim": round(m["ssim"], 4),
                "depth_error_median_pct": None if depth is None else round(100 * depth, 2),
                "train_s": round(m["train_seconds"], 1),
                "peak_gpu_gib": None if m.get("peak_gpu_memory_gib") is None else round(m["peak_gpu_memory_gib"], 2),
            }
        )
    print(f"{'object':16s} {'steps':>5s} {'PSNR dB':>8s} {'SSIM':>7s} {'depth %':>8s} {'fit s':>7s} {'GPU GiB':>8s}")
    for r in rows:
        d = "-" if r["depth_error_median_pct"] is None else f"{r['depth_error_median_pct']:.2f}"
        g = "-" if r["peak_gpu_gib"] is None else f"{r['peak_gpu_gib']:.2f}"
        cells = f"{r['steps']:5d} {r['psnr_db']:8.2f} {r['ssim']:7.4f} {d:>8s} {r['train_s']:7.1f} {g:>8s}"
        print(f"{r['object']:16s} {cells}")
    psnr = [r["psnr_db"] for r in rows]
    depth = [r["depth_error_median_pct"] for r in rows if r["depth_error_median_pct"] is not None]
    low = [r["object"] for r in rows if r["psnr_db"] < PSNR_BAR]
    print(
        f"{len(rows)} scenes: PSNR {min(psnr):.2f}-{max(psnr):.2f} dB (median {statistics.median(psnr):.2f}), "
        f"{len(low)} under {PSNR_BAR:g} dB" + (f": {', '.join(low)}" if low else "")
    )
    if depth:
        high = [r["object"] for r in rows if (r["depth_error_median_pct"] or 0) > DEPTH_BAR]
        print(
            f"median depth error {min(depth):.2f}-{max(depth):.2f} % (median {statistics.median(depth):.2f}), "
            f"{len(high)} over {DEPTH_BAR:g} %" + (f": {', '.join(high)}" if high else "")
        )
    if a.csv:
        with open(a.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    from tnf.errors import TnfError

    try:
        main()
    except TnfError as e:  # a missing or malformed metrics file: one line, as the tnf command prints it
        raise SystemExit(f"error: {e}") from None
