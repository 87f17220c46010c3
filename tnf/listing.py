"""``tnf list``: every registered component of every kind, with the package it comes from and the option that
chooses it."""

from __future__ import annotations

from tnf.registry import REGISTRIES


def component_rows() -> list[tuple[str, str, str, str, str]]:
    """(kind, name, origin, option that chooses it, one-line description) for every registered component."""
    options = _group_options()
    rows = []
    for kind, registry in REGISTRIES.items():
        for e in registry.entries():
            doc = (getattr(e.obj, "__doc__", None) or "").strip().splitlines()
            choose = f"{kind}={e.name}" if e.name in options.get(kind, ()) else _no_option(kind, e.name, e.obj)
            rows.append((kind, e.name, e.origin, choose, doc[0] if doc else ""))
    return rows


def _no_option(kind: str, name: str, obj: object) -> str:
    """What chooses a component that no config group option does: the setting its class names (``chosen_by``,
    as the mesh scene's ``pair.scene_source=mesh``), else the missing YAML (a plugin without ``tnf.conf``)."""
    return str(getattr(obj, "chosen_by", None) or f"none: no {kind}/{name}.yaml")


def _group_options() -> dict[str, list[str]]:
    """The options of each registry's config group, from tnf's configs and every plugin's (``tnf.conf``)."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from tnf.env import conf_dir

    was = GlobalHydra.instance().is_initialized()
    if was:
        return _options_now()
    with initialize_config_dir(config_dir=conf_dir(), version_base=None):
        return _options_now()


def _options_now() -> dict[str, list[str]]:
    from hydra.core.global_hydra import GlobalHydra

    loader = GlobalHydra.instance().config_loader()
    return {kind: loader.get_group_options(kind) for kind in REGISTRIES}


def print_components() -> None:
    from rich.table import Table

    from tnf.runtime import stage_console

    console = stage_console()
    rows = component_rows()
    cols = ("kind", "name", "origin", "option")
    widths = [max(len(col), *(len(r[i]) for r in rows)) for i, col in enumerate(cols)]
    # Every column but the description whole, however narrow the terminal; each description on one line, cut to the
    # width left (3 characters of border per column and 1 at the end).
    left = max(12, console.width - sum(widths) - 3 * (len(cols) + 1) - 1)
    table = Table(title="registered components", header_style="bold")
    for col, width in zip(cols, widths, strict=True):
        table.add_column(col, no_wrap=True, min_width=width)
    table.add_column("description", no_wrap=True)
    for row in rows:
        desc = row[-1] if len(row[-1]) <= left else row[-1][: left - 1] + "…"
        table.add_row(*row[:-1], desc)
    console.print(table)
