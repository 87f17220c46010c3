"""The ``tnf`` command: ``tnf STAGE [hydra overrides...]``.

Each stage is a Hydra app; all compose the one primary config ``conf/tnf.yaml`` (``tnf pipeline`` adds
``experiment=quickstart`` unless told otherwise: ``conf/stage_choices.yaml``), so ``--help``, ``--cfg job``,
``-m`` sweeps and ``key=value`` overrides work for every stage. The stage's code is
``tnf.stages.<stage>.run(cfg)``.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tnf import __version__
from tnf.artifacts import clean, data_root, data_seed_claim
from tnf.env import PRIMARY_CONFIG, conf_dir, stage_choices, stage_overrides
from tnf.errors import TnfError
from tnf.listing import print_components
from tnf.runtime import available_memory, interrupts_held
from tnf.stages.settings import check_components, check_settings, check_sizes

# name -> one line of help. Order is the pipeline's order; COMMANDS are not Hydra apps.
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
    "clean": "remove a finished item from the artifact store so that its stage redoes it (tnf clean STAGE ITEM)",
}


COMMANDS = ("list", "clean")
"""Entries of STAGES that are plain commands, not Hydra apps (no config, no overrides)."""


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
        print(f"tnf {__version__}")
        return 0
    stage, rest = argv[0], argv[1:]
    try:
        if stage not in STAGES:
            raise TnfError(f"unknown stage {stage!r}; stages: {', '.join(STAGES)} (see tnf --help)")
        if stage != "clean":
            with interrupts_held():  # trimesh swallows a Ctrl-C during its import (and imports networkx halfway)
                import trimesh  # noqa: F401
        if stage == "list":
            print_components()
            return 0
        if stage == "clean":
            print(clean(rest))
            return 0
        return run_stage(stage, rest)
    except TnfError as e:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        report_error(e)
        return 1
    except KeyboardInterrupt:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            raise
        report_error(TnfError(INTERRUPTED))
        return 130
    except BrokenPipeError:
        # The reader of the output has gone (`tnf train --help | head`): stop without a word, as other commands do.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # and no second error at exit's flush
        return 141


#: What a Ctrl-C prints: finished items are whole (each is renamed into place when complete), so a rerun resumes.
INTERRUPTED = "interrupted; run the same command again: it skips what is done and redoes the rest"


def run_stage(stage: str, overrides: Sequence[str]) -> int:
    """Run stage ``stage`` as a Hydra app with ``overrides`` (as on the command line)."""
    import hydra

    if os.environ.get("HYDRA_FULL_ERROR") != "1":
        check_overrides(stage, overrides)
    check_data_root(overrides)
    # Imported before Hydra composes: stage modules import torch-heavy code inside run(), so --help and --cfg
    # stay light.
    module = importlib.import_module(f"tnf.stages.{stage.replace('-', '_')}")
    task = _guard(module.run)
    app = hydra.main(version_base=None, config_path=conf_dir(), config_name=PRIMARY_CONFIG)(task)
    old = sys.argv
    sys.argv = [f"tnf {stage}", *_hydra_args(stage, overrides)]
    try:
        app()
    except SystemExit as e:
        return int(e.code or 0) if not isinstance(e.code, str) else 1
    except ValueError as e:  # Hydra refuses two modes at once (-m with --cfg) by a bare ValueError
        if str(e).startswith("Only one of "):
            raise TnfError(f"{e} (-m runs a sweep; --cfg prints one job's config: give one of them)") from None
        raise
    finally:
        sys.argv = old
        _forget_hydra_job()
    return 0


def _forget_hydra_job() -> None:
    """Clear the job config Hydra keeps after an app returns (``--cfg job`` leaves one without a run folder), so
    that code run later in this process (the API, another stage) does not take it for its own Hydra job."""
    from hydra.core.hydra_config import HydraConfig

    HydraConfig.instance().cfg = None  # type: ignore[assignment]


def _hydra_args(stage: str, args: Sequence[str]) -> list[str]:
    """The command line Hydra gets: ``args`` with the stage's job name (it names the run folder
    ``logs/stage/<name>/`` and the log file) and its group choices (``conf/stage_choices.yaml``), placed next to
    the user's overrides. Hydra's parser takes a single run of overrides, so every override goes first and the
    flags (``-m``, ``--cfg job``, ``--info``) after them, in their order (``a=1 -m b=2,3`` -> ``<own> a=1 b=2,3 -m``).
    """

    is_override = [not a.startswith("-") and ("=" in a or a.startswith("~")) for a in args]
    overrides = [a for a, o in zip(args, is_override, strict=True) if o]
    flags = [a for a, o in zip(args, is_override, strict=True) if not o]
    own = [f"hydra.job.name={stage.replace('-', '_')}", *stage_choices(stage, overrides)]
    return [*own, *overrides, *flags]


# Flags with which Hydra only prints something (help, config, info): no run folder, so nothing to check.
_PRINT_ONLY = {"--help", "-h", "--hydra-help", "--cfg", "-c", "--info", "-i", "--shell-completion", "-sc"}
# Less free space than this in the data root and Hydra may fail writing its run folder (config, log) already.
MIN_FREE_BYTES = 1_000_000


def check_data_root(overrides: Sequence[str]) -> None:
    """Refuse, as one line, a data root that cannot hold the run: Hydra makes its run folder
    ``<data_root>/logs/...`` before the stage starts, and a failure there is a traceback.

    The data root is the ``data_root=`` override, else ``$TNF_DATA``, else ``./tnf-data`` (as in
    ``tnf.artifacts.data_root``). Sweeps over ``data_root`` and interpolated values are left unchecked. The folder
    is created here when missing (Hydra would create it a moment later anyway).
    """
    if any(o.split("=")[0] in _PRINT_ONLY for o in overrides):
        return
    configured = _data_root_override(overrides)
    if configured is _UNCHECKED:
        return

    root = data_root(configured)  # type: ignore[arg-type]
    _check_folder(root, root)
    free = _free_bytes(root)
    if free is not None and free < MIN_FREE_BYTES:
        raise TnfError(f"no space left on device for data_root {root}: {free / 1e6:.2f} MB free")
    _check_folder(root / "logs", root)


_UNCHECKED = object()


def _data_root_override(overrides: Sequence[str]) -> object:
    """The last ``data_root=`` override's value (str or None when not given), or ``_UNCHECKED`` for a sweep or an
    interpolation, whose folder only Hydra knows."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    value: object = None
    parser = OverridesParser.create()
    for o in overrides:
        if o.startswith("-") or "data_root" not in o.split("=")[0]:
            continue
        try:
            (parsed,) = parser.parse_overrides([o])
        except Exception:  # a malformed override: Hydra reports it itself
            continue
        if parsed.key_or_group != "data_root":
            continue
        if parsed.is_delete():
            value = None
        elif parsed.is_sweep_override():
            return _UNCHECKED
        else:
            v = parsed.value()
            value = None if v is None else str(v)
    if isinstance(value, str) and "${" in value:
        return _UNCHECKED
    return value


def _check_folder(folder: Path, root: Path) -> None:
    """Make ``folder`` (the data root or a folder in it) if missing; a TnfError naming ``root`` if it cannot be."""
    name = f"data_root {root}" if folder == root else f"data_root {root}: {folder}"
    if folder.exists():
        if not folder.is_dir():
            raise TnfError(f"{name} is a file, not a folder")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise TnfError(f"{name} {_unwritable(folder)}")
        return
    ancestor = folder.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise TnfError(f"{name} cannot be created: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise TnfError(f"{name} cannot be created: {ancestor} {_unwritable(ancestor)}")
    try:  # root may write where os.access says no, and may not write where it says yes (/proc, read-only mounts)
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        import errno

        reason = (e.strerror or type(e).__name__).lower()
        if e.errno == errno.ENOENT:  # /proc, /sys: the folder is there but takes no new entries
            reason = f"{ancestor} takes no new folders"
        elif e.errno == errno.ENOTDIR:
            reason = "a folder above it is a file"
        raise TnfError(f"{name} cannot be created: {reason}") from None


def _unwritable(folder: Path) -> str:
    """Why ``folder``, which ``os.access`` calls unwritable, is."""
    try:
        if os.statvfs(folder).f_flag & os.ST_RDONLY:
            return "is on a read-only file system"
    except (OSError, AttributeError):  # no statvfs (Windows)
        pass
    return "is not writable (permission denied)"


def _free_bytes(folder: Path) -> int | None:
    import shutil

    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def check_overrides(stage: str, overrides: Sequence[str]) -> None:
    """Compose the stage's config with ``overrides`` before Hydra runs it, so that an unknown option, a misspelled
    key or a malformed value is one line (a TnfError) instead of Hydra's report with its search path.

    A sweep (``-m a=x,y b=z``) is checked one value at a time: each swept value with the others' first values.
    ``--cfg job`` (printing the config) is checked as a run is; Hydra's other flags and ``hydra...`` overrides are
    left to Hydra itself.
    """
    multirun = {"-m", "--multirun"}
    # Printing the config (--cfg job) checks the overrides too; Hydra's other flags are left to Hydra.
    printing = {"--cfg", "-c", "--resolve", "job", "hydra", "all"}
    overrides = [o for o in overrides if o not in printing or "=" in o]
    if any((o.startswith("-") and o not in multirun) or o.lstrip("+~").startswith("hydra") for o in overrides):
        return
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException, MissingConfigException
    from omegaconf.errors import OmegaConfBaseException

    name = PRIMARY_CONFIG
    plain = [o for o in overrides if o not in multirun]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=conf_dir(), version_base=None):
            for plain_combo in _combinations(plain) if len(plain) < len(overrides) else [plain]:
                combination = stage_overrides(stage, plain_combo)
                try:
                    cfg = compose(config_name=name, overrides=combination)
                except MissingConfigException as e:
                    raise TnfError(_missing_option(e, combination)) from None
                except (HydraException, OmegaConfBaseException) as e:
                    cause = e.__cause__
                    if isinstance(cause, OmegaConfBaseException) and "Could not override" in str(e):
                        chosen = _choices_only(compose, name, stage, plain_combo)
                        raise TnfError(_unknown_key(str(e), chosen, stage)) from None
                    lines = [ln for ln in str(e).splitlines() if ln.strip() and "search path" not in ln.lower()]
                    if "LexerNoViableAlt" in lines[0]:  # a value Hydra's grammar cannot read
                        lines = [f"{lines[0].split(':', 1)[-1].strip()}: {UNREADABLE}"]
                    raise TnfError(" ".join(lines[:2])) from None
                check_settings(cfg)  # before Hydra makes its run folder
                check_components(cfg, stage)
                check_sizes(cfg, stage)
    finally:
        GlobalHydra.instance().clear()


#: What to do with an override that Hydra's grammar cannot read (spaces, non-ASCII letters).
UNREADABLE = "cannot be read; quote a value with spaces or non-ASCII letters: \"object_names=['my mug']\""


def _combinations(overrides: list[str]) -> list[list[str]]:
    """The overrides of a sweep as plain ones: each swept value once, the other swept keys at their first value.
    Sweeps Hydra's parser cannot expand here (ranges, globs) keep only their first combination's check to Hydra."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException as e:
        raise TnfError(str(e).splitlines()[0]) from None
    values: list[list[str]] = []
    for o in parsed:
        key = o.get_key_element()
        if o.is_sweep_override():
            try:
                values.append([f"{key}={v}" for v in o.sweep_string_iterator()])
            except (HydraException, TypeError, ValueError):
                return []
        else:
            values.append([str(o.input_line)])
    out = [[v[0] for v in values]]
    for i, vs in enumerate(values):
        for v in vs[1:]:
            out.append([*(w[0] for w in values[:i]), v, *(w[0] for w in values[i + 1 :])])
    return out


def _missing_option(e: Exception, overrides: Sequence[str]) -> str:
    """``generator=foo: no such option; options: ...`` from Hydra's missing-config error; an option registered
    without its YAML names the fix."""
    import difflib
    import re

    m = re.search(r"Could not find '([^']+)'", str(e))
    missing = m.group(1) if m else str(e).splitlines()[0]
    group, _, option = missing.rpartition("/")
    options = getattr(e, "options", None) or []
    given = next((o for o in overrides if o.lstrip("+~").split("=")[0].lstrip("/") == group), f"{group}={option}")
    if not group:
        return f"no config {missing!r}"
    listed = f"options: {', '.join(options) if options else '(none)'}"
    from tnf.registry import REGISTRIES

    registry = REGISTRIES.get(group)
    if registry is not None and option in registry:  # registered, but no YAML joined the config group
        origin = registry.entry(option).origin
        return (
            f"{given}: {group} {option!r} is registered by {origin} but has no {group}/{option}.yaml; "
            f"{origin} needs a tnf.conf entry point naming the package of its YAML files (docs/plugins.md); {listed}"
        )
    close = difflib.get_close_matches(option, options, n=1, cutoff=0.6)
    return f"{given}: no such {group}" + (f" (did you mean {group}={close[0]}?)" if close else "") + f"; {listed}"


def _choices_only(compose: Callable[..., Any], name: str, stage: str, overrides: Sequence[str]) -> Any:
    """The stage's config with the group choices of ``overrides`` alone (``sensor=omnitact``, ``experiment=...``),
    not the keys they set: the settings an unknown key is compared with."""
    choices = [o for o in overrides if "=" in o and "." not in o.split("=", 1)[0]]
    try:
        return compose(config_name=name, overrides=stage_overrides(stage, choices))
    except Exception:  # a choice that fails alone: the stage's defaults
        return compose(config_name=name, overrides=stage_overrides(stage, []))


def _unknown_key(message: str, cfg: object, stage: str) -> str:
    """``trian.epochs: no such setting; did you mean train.epochs?`` from Hydra's failed override."""
    import difflib
    import re

    from omegaconf import OmegaConf

    m = re.search(r"Could not override '([^']+)'", message)
    key = m.group(1) if m else "?"
    keys: list[str] = []

    def walk(node: object, prefix: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}{k}.")
        keys.append(prefix.rstrip("."))

    walk(OmegaConf.to_container(cfg, resolve=False), "")  # type: ignore[arg-type]
    parent, _, leaf = key.rpartition(".")
    siblings = [k.rpartition(".")[2] for k in keys if k and k != parent and k.rpartition(".")[0] == parent]
    close = [f"{parent}.{k}" if parent else k for k in difflib.get_close_matches(leaf, siblings, n=1, cutoff=0.6)]
    close = close or difflib.get_close_matches(key, [k for k in keys if k], n=1, cutoff=0.75)  # another section
    hint = f"did you mean {close[0]}?" if close else f"see `tnf {stage} --cfg job` for the settings"
    if "." in key:  # a section's keys are its settings' fields: a new key is refused too
        return f"{key}: no such setting; {hint}"
    return f"{key}: no such setting; {hint} (+{key}=... adds a new key)"


def _guard(fn: Callable[..., object]) -> Callable[..., object]:
    """Print a TnfError as one line and exit 1, instead of Hydra's traceback report."""

    def task(cfg: object) -> object:

        try:
            try:
                stage = str(getattr(fn, "__module__", "")).rpartition(".")[2]
                check_settings(cfg)  # every job of a sweep checks its own settings before any work
                check_sizes(cfg, stage)
                with _data_claim(cfg, stage):
                    return fn(cfg)
            except (MemoryError, RuntimeError) as e:
                if isinstance(e, RuntimeError) and not _is_out_of_memory(e):
                    raise
                raise TnfError(_out_of_memory(str(getattr(fn, "__module__", "")).rpartition(".")[2], e)) from e
        except TnfError as e:
            if os.environ.get("HYDRA_FULL_ERROR") == "1":
                raise
            report_error(e)
            raise SystemExit(1) from None

    task.__name__ = getattr(fn, "__name__", "task")
    task.__module__ = getattr(fn, "__module__", __name__)
    return task


# The stages that make a data seed's items (capture, scenes, touches, pairs). Stages that only read them (train,
# generate, evaluate) take none: a sweep over seeds may train on one store's pairs side by side.
_DATA_STAGES = {"capture", "fit-scene", "touch", "pair"}


def _data_claim(cfg: Any, stage: str) -> contextlib.AbstractContextManager[None]:
    """The claim of a stage that makes data items (a pipeline that runs one) on its store for its data seed
    (``tnf.artifacts.data_seed_claim``): a run making another data seed's items in the same ``data_root`` at the
    same time stops with one line instead of replacing them."""
    stages = {stage.replace("_", "-")}
    if stage == "pipeline":
        stages = {str(s) for s in cfg.pipeline.stages}
    if not stages & _DATA_STAGES:
        return contextlib.nullcontext()
    from tnf.stages import data_seed

    return data_seed_claim(data_root(cfg.data_root), data_seed(cfg), f"tnf {stage.replace('_', '-')} seed={cfg.seed}")


def _is_out_of_memory(e: BaseException) -> bool:
    """True for the errors PyTorch raises when an allocation fails (CPU or CUDA)."""
    text = str(e).lower()
    return "out of memory" in text or "can't allocate memory" in text or "cannot allocate memory" in text


def _out_of_memory(stage: str, e: BaseException) -> str:
    """One line for an allocation that failed where no estimate caught it first: what it asked, what there is."""
    import re

    m = re.search(r"allocate ([\d.]+) (bytes|[KMGT]i?B)", str(e))
    asked = ""
    if m:
        scale = {"bytes": 1, "KiB": 2**10, "MiB": 2**20, "GiB": 2**30, "TiB": 2**40}.get(m.group(2), 1)
        asked = f" asking for {float(m.group(1)) * scale / 2**30:.1f} GiB"
    have = available_memory()
    free = f"; this machine has {have / 2**30:.1f} GiB available" if have is not None else ""
    return (
        f"tnf {stage.replace('_', '-')} ran out of memory{asked}{free}: lower the settings that size its work "
        "(batch sizes, batch_rays, resolutions, sensor.width and sensor.height)"
    )


def report_error(e: BaseException) -> None:
    from rich.console import Console
    from rich.markup import escape

    console = Console(stderr=True, highlight=False, soft_wrap=True)
    console.print(f"[bold red]error:[/] {escape(str(e))}", markup=True, emoji=False)  # "[1, 2]" is not markup


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
