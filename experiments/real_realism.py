"""Realism against real GelSight frames: every way tnf makes a press, and Taxim, in one table.

On a recording that the ``taxim`` package ships, all on the CPU. The GelSight Mini's (``--recording
gelsight_mini``, the default) splits as ``conf/calibrate/default.yaml`` does: presses 0-15 train, 16-23 held out.
Any other recording splits by the same rule, the first two thirds train and the rest are held out
(``--recording gelsight``: 48 presses, 0-31 and 32-47). Every recording is simulated with the GelSight Mini's
geometry (``conf/sensor/gelsight_mini.yaml``); taxim's recordings share its image size and pixel size:

1. tnf's calibration fitted on presses 0-15 at 320x240 (``tnf calibrate``'s defaults): the no-contact frame,
   the hand-set optics, the calibration at 320x240 and rendered at the recording's 640x480.
2. Taxim (its JAX backend, its own calibration of this sensor, with its shadows) at its native 640x480.
3. T-N: ``tnf pipeline experiment=sim_gelsight_mini`` up to training (the Mini calibrated at 160x120 with the
   same settings, five objects with a 5 mm bearing ball among the training ones, T-N trained on the calibrated
   simulator's pairs), then the indenter rendered as RGB-D at each held-out press's pose with the mesh scene and
   fed to that generator, its depth measured from the pressed gel (a deeper press comes closer; ``tnf finetune``'s
   default) and, in a second row, from the first contact (the convention of the simulated pairs it trained on).
   ``--experiment sim_gelsight_mini_gpu --device cuda`` trains it at sim_digit's scale
   instead (28 objects, the Mini at 320x240); ``--no-taxim`` leaves out Taxim where JAX is missing.
4. T-N fine-tuned on the real frames of the training presses (``transfer=real``'s settings) and the same network
   from scratch on those frames (FS). With ``--tn-plus``, also T-N+ (simulated pairs kept in the mix; about a
   minute more).

Each held-out press sits at its annotated centre. Scores: :mod:`tnf.real.report` (the native 4r crop with
the sharpness ratio, and the contact region at 320x240).

    python experiments/real_realism.py --out results/real/gelsight_mini
    python experiments/real_realism.py --recording gelsight --out results/real/gelsight
    python experiments/real_realism.py --experiment sim_gelsight_mini_gpu --device cuda --no-taxim \
        --out results/real/gelsight_mini_gpu

Writes ``report.md``, ``realism.png`` and ``realism.json`` into ``--out``; the pipeline's data and the
fine-tuned runs go to ``--data-root`` (default: a temporary folder; pass one to reuse its runs; one recording per
folder).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

PIPELINE = "[calibrate,capture,fit-scene,touch,pair,train]"
RECORDINGS = {"gelsight_mini": "GelSight Mini", "gelsight": "GelSight"}


def split(recording: str, n: int, conf: Path) -> tuple[list[int], list[int]]:
    """Training and held-out presses of a recording of ``n`` presses: ``conf/calibrate``'s for the GelSight Mini,
    else the first two thirds and the rest (the Mini's split by the same rule)."""
    if recording == "gelsight_mini":
        from omegaconf import OmegaConf

        cal = OmegaConf.load(conf / "calibrate" / "default.yaml")
        return list(cal.train), list(cal.test)
    k = round(2 * n / 3)
    return list(range(k)), list(range(k, n))


def taxim_frames(recording: str, presses, indices, with_shadow: bool = True) -> tuple[np.ndarray, float]:
    """Taxim's frames ``[N, 480, 640, 3]`` uint8 of the presses, and its warm seconds per frame.

    Taxim presses to the depth at which the ball crosses the gel in the annotated circle, as its calibration
    defines it."""
    from taxim import CALIB_GELSIGHT, CALIB_GELSIGHT_MINI, Taxim

    calib = {"gelsight_mini": CALIB_GELSIGHT_MINI, "gelsight": CALIB_GELSIGHT}[recording]
    sim = Taxim(calib_folder=calib, backend="jax")
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


def calibration_name(recording: str, width: int, height: int) -> str:
    """The name of the pipeline's calibration at ``width x height`` (``calibrate.name``) made on ``recording``."""
    return f"mini_{width}x{height}" if recording == "gelsight_mini" else f"{recording}_{width}x{height}"


def pipeline_settings(experiment: str, seed: int, overrides: list[str]) -> dict:
    """What this script takes from the pipeline's config: the sensor's size and the trainer (Lightning's
    arguments). An unknown experiment or setting exits with the one line `tnf` gives it."""
    from omegaconf import OmegaConf

    from tnf.cli import check_overrides
    from tnf.errors import TnfError
    from tnf.testing.config import hydra_job

    settings = [f"experiment={experiment}", f"seed={seed}", *overrides]
    try:
        check_overrides("pipeline", settings)
    except TnfError as e:
        sys.exit(f"real_realism.py: {e}")
    with hydra_job("pipeline", settings) as cfg:
        return {
            "width": int(cfg.sensor.width),
            "height": int(cfg.sensor.height),
            "trainer": OmegaConf.to_container(cfg.trainer, resolve=True),
        }


def claim_root(root: Path, recording: str) -> None:
    """Mark ``root`` as holding ``recording``'s runs; exit with one line if it holds another recording's.

    The pipeline names its pairs and its T-N by the sensor, not by the recording its calibration came from: two
    recordings in one data root would share them."""
    marker = root / "realism_recording.txt"
    held = marker.read_text().strip() if marker.is_file() else None
    if held is None and any((root / "models").glob("tn_cgan_plain-*")):  # a root of before the marker: the Mini's
        held = "gelsight_mini"
    if held is not None and held != recording:
        sys.exit(f"--data-root {root} holds the runs of the {held} recording; give another for --recording {recording}")
    root.mkdir(parents=True, exist_ok=True)
    marker.write_text(recording + "\n")


def pipeline_args(
    root: Path, seed: int, recording: str, train: list[int], test: list[int], experiment: str,
    overrides: list[str], size: tuple[int, int],
) -> list[str]:  # fmt: skip
    """The settings of ``tnf pipeline experiment=EXPERIMENT`` up to training into ``root``, its calibration made
    on the training presses of ``recording``."""
    args = [f"experiment={experiment}", f"data_root={root}", f"seed={seed}", "progress=false"]
    args += [f"pipeline.stages={PIPELINE}"]
    if recording != "gelsight_mini":  # the Mini's run keeps the experiment's settings, and so its identity
        args += [f"calibrate.presses=taxim:{recording}", f"calibrate.train={train}", f"calibrate.test={test}"]
        args += [f"calibrate.name={calibration_name(recording, *size)}"]
    return [*args, *overrides]


def run_pipeline(root: Path, args: list[str]) -> tuple[str, float]:
    """Run ``tnf pipeline ARGS`` (every stage whose work is there finds it done); the model run it trained (the
    folder under ``root/models``, named from its settings and its dataset, ``tnf.stages.train.model_run``) and
    its wall seconds.

    Run alone: beside the 320x240 calibration, both slowed each other down on 2 cores (the scene fits took twice
    as long) and the whole script gained nothing."""
    from tnf.stages.train import model_run
    from tnf.testing.config import hydra_job

    t0 = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "tnf.cli", "pipeline", *args], check=True, env={**os.environ, "TNF_DATA": str(root)}
    )
    seconds = time.perf_counter() - t0
    with hydra_job("pipeline", args) as cfg:
        return model_run(cfg), seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recording", default="gelsight_mini", choices=sorted(RECORDINGS), help="taxim's recording")
    ap.add_argument("--out", default=None, help="report.md and realism.png go here (default: results/real/RECORDING)")
    ap.add_argument("--data-root", default=None, help="the pipeline's and fine-tuning's data (default: temporary)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tn-plus", action="store_true", help="also T-N+: fine-tuned with simulated pairs kept")
    ap.add_argument("--experiment", default="sim_gelsight_mini", help="the pipeline that trains T-N")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where T-N and the fine-tunings train")
    ap.add_argument("--no-taxim", action="store_true", help="leave Taxim's row out (it needs JAX)")
    ap.add_argument(
        "--no-simulator", action="store_true",
        help="leave the simulator's rows out (their fit and renders run Warp on the CPU); the pipeline's own "
        "calibration is still made, or found in --data-root",
    )  # fmt: skip
    ap.add_argument("overrides", nargs="*", help="more settings of the pipeline (key=value), e.g. for a small run")
    args = ap.parse_args()

    from omegaconf import OmegaConf

    from tnf.real import report
    from tnf.real.calibrate import FitSettings, calibration_rows, fit_calibration, fit_summary
    from tnf.real.finetune import finetune_on_presses
    from tnf.real.generated import checkpoint_framing, generate_presses
    from tnf.real.presses import at_sensor_size, resolve_presses
    from tnf.registry import SENSORS, from_dict
    from tnf.runtime import environment

    started = time.perf_counter()
    # The pipeline's settings first: a wrong one stops the script before anything is written.
    overrides = [*(["trainer=gpu"] if args.device == "cuda" else []), *args.overrides]
    pipe = pipeline_settings(args.experiment, args.seed, overrides)
    root = Path(args.data_root or tempfile.mkdtemp(prefix="tnf-realism-"))
    claim_root(root, args.recording)
    out = Path(args.out or f"results/real/{args.recording}")
    sensor_name = RECORDINGS[args.recording]
    out.mkdir(parents=True, exist_ok=True)
    conf = Path(__file__).resolve().parents[1] / "conf"
    cal_cfg = OmegaConf.load(conf / "calibrate" / "default.yaml")
    settings = from_dict(FitSettings, OmegaConf.to_container(cal_cfg.fit), where="calibrate.fit")
    presses = resolve_presses(f"taxim:{args.recording}", root)
    train, test = split(args.recording, len(presses), conf)
    wall: dict[str, float] = {}

    # 1. tnf's calibration at 320x240.
    sensor = SENSORS.build("gelsight_mini")
    info: dict | None = None
    if args.no_simulator:
        rows, sp = [], at_sensor_size(presses, sensor, test)
    else:
        t0 = time.perf_counter()
        warp = {"name": "warp_gel"}
        cal, info = fit_calibration(presses, sensor, warp, train, settings)
        cal.save(root / "calibration_320x240")
        rows, sp = calibration_rows(presses, sensor, cal, info, warp, test, str(root / "calibration_320x240"))
        wall["calibration (fit and renders)"] = time.perf_counter() - t0
        print(f"calibration: {wall['calibration (fit and renders)']:.0f} s", flush=True)

    # 2. Taxim.
    if not args.no_taxim:
        t0 = time.perf_counter()
        taxim, taxim_s = taxim_frames(args.recording, presses, test)
        rows.append(report.Row("Taxim", taxim, taxim_s))
        wall["Taxim"] = time.perf_counter() - t0
        print(f"Taxim: {wall['Taxim']:.0f} s", flush=True)

    # 3. T-N trained on the calibrated simulator's pairs.
    # The pipeline's model: the run its settings and dataset name (a data root holding another setting's run
    # trains a new one).
    size = (pipe["width"], pipe["height"])
    run, wall["pipeline to T-N"] = run_pipeline(
        root, pipeline_args(root, args.seed, args.recording, train, test, args.experiment, overrides, size)
    )
    ckpt = root / "models" / run / "best.ckpt"
    if not ckpt.is_file():
        sys.exit(f"real_realism.py: the pipeline left no model at {ckpt.parent}")
    small_cal = root / "calibration" / "gelsight_mini" / calibration_name(args.recording, *size)
    small = SENSORS.build({"name": "gelsight_mini", "width": size[0], "height": size[1], "calibration": str(small_cal)})
    small_info = json.loads((small_cal / "realism.json").read_text())["fit"]
    depth_scale = float(small_info["depth_scale"])
    framing = checkpoint_framing(ckpt)
    small_sp = at_sensor_size(presses, small, test)
    radius = presses.radius_mm * 1e-3

    def generated(checkpoint: Path, reference: str = "gel") -> tuple[np.ndarray, float]:
        t = time.perf_counter()
        images = generate_presses(
            checkpoint, small, small_sp, radius, depth_scale, framing=framing, reference=reference
        )
        return images, (time.perf_counter() - t) / len(test)

    rows.append(report.Row("T-N (simulator only)", *generated(ckpt)))
    rows.append(report.Row("T-N (simulator only), depth from the first contact", *generated(ckpt, "contact")))

    # 4. Few-shot on the real frames of the training presses.
    import torch

    ft = OmegaConf.load(conf / "transfer" / "real.yaml").finetune
    # The experiment's trainer, as `tnf finetune experiment=EXPERIMENT` has it (with trainer=gpu on a GPU).
    trainer = pipe["trainer"]
    batch = 16
    steps = int(ft.epochs) * -(-len(train) // batch)  # the presses' batches per epoch, times its epochs
    spec = torch.load(ckpt, weights_only=False, map_location="cpu")["tnf"]["generator"]
    lr = float(ft.lr) if ft.lr is not None else None
    runs = {"T-N fine-tuned": ("T-N", ckpt, 0), "FS (real presses only)": ("FS", None, 0)}
    if args.tn_plus:
        runs["T-N+ (fine-tuned, simulated pairs kept)"] = ("T-N+", ckpt, 16)
    # Each under the T-N run it starts from or takes its framing from: a data root reused with other settings
    # fine-tunes again.
    sim_pairs = root / "pairs" / json.loads((root / "models" / run / "manifest.json").read_text())["datasets"][0]
    for label, (short, source, n_sim) in runs.items():
        t0 = time.perf_counter()
        tuned = finetune_on_presses(
            source, presses, small, train, root / "real_finetune" / run / short, steps, batch_size=batch,
            lr=lr, generator=dict(spec), framing=framing, depth_scale=depth_scale,
            sim=sim_pairs if n_sim else None, sim_pairs=n_sim, seed=args.seed,
            val_every_n_epochs=int(ft.val_every_n_epochs), trainer=trainer,
        )  # fmt: skip
        wall[f"{label}: training"] = time.perf_counter() - t0
        rows.append(report.Row(label, *generated(tuned)))
        print(f"{label}: {wall[f'{label}: training']:.0f} s", flush=True)

    env = environment(args.device)
    total = time.perf_counter() - started
    intro = [f"Held-out presses {test[0]}-{test[-1]} of the {sensor_name} recording in the `taxim` package."]
    if info is not None:
        summary = fit_summary(info, settings, "320x240")
        intro[0] += f" tnf's calibration at 320x240: {summary[0]}"
        intro += [x for x in summary if x.startswith("Warning")]
    intro += [
        f"T-N: `tnf pipeline experiment={args.experiment}` (seed {args.seed}"
        + (f"; {' '.join(args.overrides)}" if args.overrides else "")
        + f"), the GelSight Mini's geometry calibrated on this recording's presses {train[0]}-{train[-1]} at "
        f"{size[0]}x{size[1]} with the same settings, a 5 mm bearing ball among its training objects; its touches "
        "of the indenter (a sphere of the recorded radius, the mesh scene) at each held-out press, "
        f"{size[0]}x{size[1]}, upsampled. Fine-tuned and FS: "
        f"{steps} batches at the generator's own learning rate on the real frames of presses "
        f"{train[0]}-{train[-1]} (`transfer=real`)."
        + (" T-N+ keeps 16 of the pipeline's simulated pairs in the mix." if args.tn_plus else ""),
        (
            "Taxim: its JAX backend and its own calibration of this sensor (made from this recording, the held-out "
            "presses included), with its shadows, at 640x480. "
            if not args.no_taxim
            else ""
        )
        + "Every source sits at the annotated centres.",
        "",
        "Wall time on this machine: "
        + ", ".join(f"{k} {v:.0f} s" for k, v in wall.items())
        + f"; {total:.0f} s in all.",
        "",
        f"Machine: {env['accelerator']} ({env['cpu_cores']} cores), Python {platform.python_version()}, "
        f"warp {env['warp']}, tnf commit {env['commit']}. Reproduce: "
        f"`pip install -e '.[real]' && python experiments/real_realism.py --recording {args.recording}"
        + (" --tn-plus" if args.tn_plus else "")
        + (f" --experiment {args.experiment}" if args.experiment != "sim_gelsight_mini" else "")
        + (f" --device {args.device}" if args.device != "cpu" else "")
        + (" --no-taxim" if args.no_taxim else "")
        + (" --no-simulator" if args.no_simulator else "")
        + "".join(f" {o}" for o in args.overrides)
        + "`.",
    ]
    grid = [r.name for r in rows if r.name.endswith("640x480")]
    grid += ["T-N (simulator only)", "T-N fine-tuned"] + ([] if args.no_taxim else ["Taxim"])
    record = report.write_report(
        out, f"Realism against real {sensor_name} frames", intro, rows, presses, sp, grid_rows=grid,
        region_scale=settings.region_scale, extra={"fit": info, "wall_s": wall, "total_s": total},
    )  # fmt: skip
    (out / "realism.md").rename(out / "report.md")
    print(report.table(record["mean"], record["seconds_per_frame"]))
    print(f"{total:.0f} s in all; report: {out / 'report.md'}")


if __name__ == "__main__":
    main()
