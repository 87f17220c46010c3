"""``tnf list``: every registered component of every kind, with the package it comes from."""

from __future__ import annotations

from tnf.registry import REGISTRIES


def component_rows() -> list[tuple[str, str, str, str]]:
    """(kind, name, origin, one-line description) for every registered component."""
    rows = []
    for kind, registry in REGISTRIES.items():
        for e in registry.entries():
            doc = (getattr(e.obj, "__doc__", None) or "").strip().splitlines()
            rows.append((kind, e.name, e.origin, doc[0] if doc else ""))
    return rows


def print_components() -> None:
    from rich.table import Table

    from tnf.runtime import stage_console

    table = Table(title="registered components", header_style="bold")
    for col in ("kind", "name", "origin", "description"):
        table.add_column(col)
    for row in component_rows():
        table.add_row(*row)
    stage_console().print(table)
