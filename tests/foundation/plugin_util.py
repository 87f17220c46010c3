"""Install the tiny test plugin the way pip would leave it: the package plus a dist-info folder."""

import shutil
import sys
from pathlib import Path

TINY = Path(__file__).resolve().parents[1] / "fixtures" / "tiny_plugin"


def install_tiny_plugin(
    site: Path,
    broken: bool = False,
    sensor: str = "tnf_tiny_plugin.sensor:TinySensor",
    conf: str = "tnf_tiny_plugin.conf",
) -> Path:
    """Install into ``site``; ``sensor`` and ``conf`` are its entry points' targets, ``broken`` makes its sensor
    module import a package that is not installed."""
    # A fresh install each time: forget modules a previous test imported from another copy.
    for mod in [m for m in sys.modules if m.split(".")[0] == "tnf_tiny_plugin"]:
        del sys.modules[mod]
    site.mkdir(parents=True, exist_ok=True)
    shutil.copytree(TINY / "src" / "tnf_tiny_plugin", site / "tnf_tiny_plugin")
    if broken:
        (site / "tnf_tiny_plugin" / "sensor.py").write_text("import tnf_missing_dependency_xyz\n")
    info = site / "tnf_tiny_plugin-0.0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: tnf-tiny-plugin\nVersion: 0.0.1\n")
    (info / "entry_points.txt").write_text(f"[tnf.sensors]\ntiny = {sensor}\n\n[tnf.conf]\ntiny = {conf}\n")
    (info / "RECORD").write_text("")
    return site
