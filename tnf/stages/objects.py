"""``tnf objects objects=SOURCE``: list the objects of an object source with size and triangle count."""

from __future__ import annotations

from typing import Any

from tnf.runtime import progress, stage_console
from tnf.stages import run_objects


def run(cfg: Any) -> list[dict[str, Any]]:
    """Print a table of the selected objects (name, size in cm, triangles); returns its rows. A one-line
    TnfError (exit 1) after the table when none of them is a valid mesh."""
    from rich.table import Table

    source, names = run_objects(cfg, usable=False)  # each invalid one is a row left out, counted below
    rows: list[dict[str, Any]] = []
    with progress(cfg.progress, transient=True) as p:
        task = p.add_task(f"loading {source.name}", total=len(names))
        for name in names:
            mesh = source.load_or_skip(name)
            if mesh is not None:
                size = [float(x) * 100 for x in mesh.extents]
                assert mesh.visual is not None  # a Trimesh always has visuals
                rows.append({"name": name, "size_cm": size, "triangles": len(mesh.faces), "colour": mesh.visual.kind})
            p.advance(task)
    table = Table(title=f"objects of source {source.name!r} ({len(rows)} of {len(names)} valid)", header_style="bold")
    for col, just in (("name", "left"), ("size (cm)", "right"), ("triangles", "right"), ("colour", "left")):
        table.add_column(col, justify=just)  # type: ignore[arg-type]
    for r in rows:
        table.add_row(r["name"], " x ".join(f"{x:.1f}" for x in r["size_cm"]), str(r["triangles"]), str(r["colour"]))
    stage_console().print(table)
    if names and not rows:
        source.usable(names)  # a one-line TnfError: no valid object, with the first one's reason
    return rows
