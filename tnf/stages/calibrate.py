"""``tnf calibrate``: fit a sensor's optics to real indenter presses and score realism on held-out presses.

Writes ``<data_root>/calibration/<sensor>/<name>/``: ``calibration.npz`` and ``background.png`` (what
``sensor.calibration=<that folder>`` makes every later stage use), ``realism.md``, ``realism.json``,
``realism.png`` and the manifest. ``calibrate.presses=taxim:gelsight_mini`` first imports the recording that the
``taxim`` package ships into ``<data_root>/presses/taxim_gelsight_mini/``.
"""

from __future__ import annotations

from typing import Any

from tnf.artifacts import ArtifactStore, identity
from tnf.real.calibrate import CalibrateSettings, calibrate_sensor, search_steps
from tnf.real.presses import presses_digest, resolve_presses
from tnf.real.report import table
from tnf.registry import SENSORS, from_dict, split_spec
from tnf.runtime import progress, stage_console
from tnf.sim.base import simulator_key


def run(cfg: Any) -> dict[str, Any] | None:
    console = stage_console()
    c = from_dict(CalibrateSettings, cfg.calibrate, where="calibrate")
    store = ArtifactStore(cfg.data_root)
    presses = resolve_presses(c.presses, cfg.data_root)
    # The sensor as it is before calibration: an experiment may already point sensor.calibration at this output.
    sensor_name, sensor_spec = split_spec(cfg.sensor, "sensor")
    sensor = SENSORS.build({"name": sensor_name, **sensor_spec, "calibration": None})
    settings = c.fit
    train, test = c.train, c.test
    name = c.name
    digest = presses_digest(presses)
    spec_name, spec = split_spec(cfg.simulator, "simulator")
    simulator = {"name": spec_name, **spec}
    # The press setting (in ``calibrate``) and the folder's content identify the presses, not the folder's path:
    # a data root copied to another machine or path keeps its calibration.
    config = {
        "presses_digest": digest,
        "sensor": sensor.describe(),
        "simulator": simulator_key(simulator),
        "calibrate": identity(c),
    }
    item = ("calibration", sensor.name, name)
    where = store.path(*item)
    if store.is_done(*item, config=config):
        console.print(f"calibrate {sensor.name}/{name}: done, skipped ({where})")
        return None
    steps = search_steps(settings)
    with progress(cfg.progress) as bar:
        task = bar.add_task(f"calibrate {sensor.name}", total=steps)
        with store.writing(*item, config=config) as tmp:
            record = calibrate_sensor(
                presses, sensor, simulator, train, test, settings, tmp,
                grid_presses=c.grid_presses, on_step=lambda _: bar.advance(task),
            )  # fmt: skip
        bar.update(task, total=len(record["fit"]["search"]))  # fewer where depth factors were left out

    for line in record["fit"]["edges"]:
        console.print(f"[yellow]warning:[/] {line}")
    console.print(table(record["mean"], record["seconds_per_frame"]))
    console.print(f"calibration: {where}\nuse it with: sensor={sensor.name} sensor.calibration={where}")
    return record
