"""How much of the calibrated simulator's gap on held-out presses is the annotated centres: a diagnostic.

Fits the calibration on the training presses (as ``experiments/real_realism.py`` does at 320x240), then scores it
on the held-out presses twice: at their annotated centres, and with each centre moved to where the fitted pattern
best matches that press's real frame (``refine_radius`` pixels at 320x240 at most, the search the fit runs on the
training presses). The second score uses the held-out frames to place the presses: it says what the optics reach
with the poses right, and is no result of the method.

Then a ceiling for any simulator placed at the annotated centres: each held-out real frame's change from the
no-contact frame, moved back by its refined shift (so its contact sits at the annotated centre), over the
no-contact frame. That image has the sensor's own optics and sharpness; what it loses is the pose error alone.

    python experiments/real_centres.py --recording gelsight_mini
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recording", default="gelsight_mini", choices=["gelsight_mini", "gelsight"])
    ap.add_argument("--data-root", default=None, help="where taxim's presses are imported (default: temporary)")
    args = ap.parse_args()

    from omegaconf import OmegaConf
    from real_realism import split

    from tnf.real import report
    from tnf.real.calibrate import FitSettings, calibration_rows, centre_shifts, fit_calibration
    from tnf.real.presses import resolve_presses
    from tnf.registry import SENSORS, from_dict

    conf = Path(__file__).resolve().parents[1] / "conf"
    settings = from_dict(
        FitSettings, OmegaConf.to_container(OmegaConf.load(conf / "calibrate" / "default.yaml").fit), where="fit"
    )
    presses = resolve_presses(f"taxim:{args.recording}", args.data_root or tempfile.mkdtemp(prefix="tnf-centres-"))
    train, test = split(args.recording, len(presses), conf)
    sensor, warp = SENSORS.build("gelsight_mini"), {"name": "warp_gel"}
    cal, info = fit_calibration(presses, sensor, warp, train, settings)

    # The held-out presses' best shifts against the fitted pattern, as the fit finds them for training presses.
    moved = centre_shifts(presses, sensor, warp, cal, info, test, settings)
    # The training presses' shifts, as the fit applied them: where the ball was, against where it is annotated.
    fitted = np.asarray(info["center_shifts_px"]) * presses.width / sensor.width
    for name, idx, shift in (("training", train, fitted), ("held-out", test, moved)):
        annotated = np.array([presses.presses[i].center for i in idx])
        print(
            f"{name} presses: annotated centres spread {annotated.std(0).round(1).tolist()} px (columns, rows), "
            f"refined {(annotated + shift).std(0).round(1).tolist()}"
        )
    refined = list(presses.presses)
    for k, i in enumerate(test):
        col, row = refined[i].center
        refined[i] = dataclasses.replace(refined[i], center=(col + moved[k, 0], row + moved[k, 1]))

    print(f"held-out presses {test[0]}-{test[-1]}: centres moved by (columns, rows), recording pixels:")
    print("  " + ", ".join(f"{i}: ({c:+.0f}, {r:+.0f})" for i, (c, r) in zip(test, moved, strict=True)))
    print(f"  mean distance {float(np.hypot(*moved.T).mean()):.1f} px, largest {float(np.hypot(*moved.T).max()):.1f}")
    ceiling = report.Row("real frames moved to the annotated centres", moved_back(presses, test, moved))
    moved_presses = dataclasses.replace(presses, presses=tuple(refined))
    for name, ps, extra in (
        ("annotated centres", presses, [ceiling]),
        ("centres refined on the held-out frames", moved_presses, []),
    ):
        rows, sp_rows = calibration_rows(ps, sensor, cal, info, warp, test, "diagnostic")
        scored = [rows[2], *extra]  # the calibration at the sensor's size, and the ceiling at the annotated centres
        for row, label in zip(scored, [name, *(r.name for r in extra)], strict=True):
            means = report.mean_scores(report.score_rows([row], ps, sp_rows))[row.name]
            print(
                f"{label}: native crop SSIM {means['ssim_crop']:.3f}, MSE {means['mse_crop']:.0f}, sharpness "
                f"{means['sharpness']:.2f}; contact region SSIM {means['ssim_region']:.3f}, "
                f"MSE {means['mse_region']:.0f}"
            )


def moved_back(presses, test, shifts: np.ndarray) -> np.ndarray:
    """Held-out real frames [N, H, W, 3] (uint8, native size) whose change from the no-contact frame is moved by
    minus ``shifts`` [N, 2] (columns, rows; bilinear), so that each contact sits at its annotated centre."""
    from scipy.ndimage import shift as move

    f0 = presses.background().astype(np.float32)
    out = []
    for k, i in enumerate(test):
        change = presses.frame(i).astype(np.float32) - f0
        back = move(change, (-shifts[k, 1], -shifts[k, 0], 0.0), order=1, mode="constant", cval=0.0)
        out.append(np.clip(np.rint(f0 + back), 0, 255).astype(np.uint8))
    return np.stack(out)


if __name__ == "__main__":
    main()
