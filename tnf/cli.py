"""The ``tnf`` command: ``tnf STAGE [hydra overrides...]``.

Each stage is a Hydra app whose primary config is ``conf/stage/<stage>.yaml`` (dashes become underscores), so
``--help``, ``--cfg job``, ``-m`` sweeps and ``key=value`` overrides work for every stage. The stage's code
is ``tnf.stages.<stage>.run(cfg)``.
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable, Sequence

from tnf.errors import TnfError

# name -> one line of help. Order is the pipeline's order.
STAGES: dict[str, str] = {
    "list": "list every registered component (objects, scenes, sensors, simulators, generators) and its origin",
    "objects": "list the objects of an object source with size and triangle count",
    "capture": "render multi-view RGB-D images of objects (transforms.json, RGBA PNGs, depth)",
    "fit-scene": "fit a scene representation (nerf, hashgrid) to an object's captured views",
    "calibrate": "fit a sensor's optics to real indenter presses; score realism on held-out presses",
    "touch": "simulate tactile touches of objects with a sensor (warp gel simulator)",
    "pair": "pair each touch with RGB-D rendered from the object's scene; build a dataset",
    "train": "train a generator (tn_cgan, lee, cyclegan) on a paired dataset",
    "finetune": "fine-tune a trained generator on a small dataset of another sensor",
    "generate": "generate tactile images from novel poses with a trained generator",
    "evaluate": "compute SSIM/MSE and the classification task; write the report",
    "pipeline": "run every stage in order for one experiment",
}


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    verbose = False
    for flag in ("--verbose", "-v"):
        while flag in argv[:1]:
            argv.remove(flag)
            verbose = True
    if verbose:
        os.environ["HYDRA_FULL_ERROR"] = "1"
    if not argv or argv[0] in ("-h", "--help", "help"):
        _print_help()
        return 0
    if argv[0] in ("--version", "version"):
        from tnf import __version__

        print(f"tnf {__version__}")
        return 0
    stage, rest = argv[0], argv[1:]
    try:
        if stage not in STAGES:
            raise TnfError(f"unknown stage {stage!r}; stages: {', '.join(STAGES)} (see tnf --help)")
        if stage == "list":
            from tnf.listing import print_components

            print_components()
            return 0
        return run_stage(stage, rest)
    except TnfError as e:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        report_error(e)
        return 1


def run_stage(stage: str, overrides: Sequence[str]) -> int:
    """Run stage ``stage`` as a Hydra app with ``overrides`` (as on the command line)."""
    import hydra

    from tnf.env import conf_dir

    module = importlib.import_module(f"tnf.stages.{stage.replace('-', '_')}")
    task = _guard(module.run)
    app = hydra.main(version_base=None, config_path=conf_dir(), config_name="stage/" + stage.replace("-", "_"))(task)
    old = sys.argv
    sys.argv = [f"tnf {stage}", *overrides]
    try:
        app()
    except SystemExit as e:
        return int(e.code or 0) if not isinstance(e.code, str) else 1
    finally:
        sys.argv = old
    return 0


def _guard(fn: Callable[..., object]) -> Callable[..., object]:
    """Print a TnfError as one line and exit 1, instead of Hydra's traceback report."""

    def task(cfg: object) -> object:
        try:
            return fn(cfg)
        except TnfError as e:
            if os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            report_error(e)
            raise SystemExit(1) from None

    task.__name__ = getattr(fn, "__name__", "task")
    task.__module__ = getattr(fn, "__module__", __name__)
    return task


def report_error(e: BaseException) -> None:
    from rich.console import Console

    Console(stderr=True, highlight=False, soft_wrap=True).print(f"[bold red]error:[/] {e}", markup=True, emoji=False)


def _print_help() -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console(highlight=False)
    console.print("[bold]tnf[/] - tactile sensor data from camera images\n")
    console.print("usage: tnf \\[--verbose] STAGE \\[key=value ...] \\[-m] \\[--help] \\[--cfg job]\n")
    table = Table(show_header=True, header_style="bold", box=None, pad_edge=False)
    table.add_column("stage")
    table.add_column("what it does")
    for name, line in STAGES.items():
        table.add_row(name, line)
    console.print(table)
    console.print(
        "\n`tnf STAGE --help` shows a stage's config groups and options; `tnf STAGE --cfg job` its config."
        "\nErrors print one line; --verbose (or HYDRA_FULL_ERROR=1) shows the full traceback."
    )


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
