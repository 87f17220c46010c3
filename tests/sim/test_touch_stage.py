import json

import numpy as np
import pytest
from PIL import Image

from tnf.cli import main


def test_touch_tiny_writes_item_and_rerun_skips(data_root, capsys):
    assert main(["touch", "debug=tiny", "object=ball", "progress=false", "device=cpu"]) == 0
    item = data_root / "touch" / "digit" / "builtin" / "ball"
    m = json.loads((item / "manifest.json").read_text())
    touches = m["touches"]
    assert [t["split"] for t in touches].count("train") == m["counts"]["train"] == 12
    assert {t["split"] for t in touches} == {"train", "val", "novel_view"}
    assert m["sensor"]["name"] == "digit" and m["source"] == "builtin" and m["object"] == "ball"
    bg = np.asarray(Image.open(item / "background.png"))
    assert bg.shape == (80, 60, 3)
    for t in touches[:3]:
        img = np.asarray(Image.open(item / t["image"]))
        assert img.shape == (80, 60, 3)
        assert t["force"] > 0 and 0 < t["penetration"] < 0.003
        start, contact = np.array(t["start_c2w"]), np.array(t["contact_c2w"])
        # The sensor moved along its own -z axis from the start pose to the contact pose.
        step = contact[:3, 3] - start[:3, 3]
        assert np.allclose(np.cross(step, -start[:3, 2]), 0, atol=1e-6) and step @ -start[:3, 2] > 0
        assert np.allclose(contact[:3, :3], start[:3, :3])
    # The held-out cone: novel-view starts lie within 30 degrees of +x, the others outside it.
    for t in touches:
        p = np.array(t["start_c2w"])[:3, 3]
        inside = p[0] / np.linalg.norm(p) >= np.cos(np.radians(30)) - 1e-9
        assert inside == (t["split"] == "novel_view")
    mtime = (item / "manifest.json").stat().st_mtime_ns
    capsys.readouterr()
    assert main(["touch", "debug=tiny", "object=ball", "progress=false", "device=cpu"]) == 0
    assert "skipped" in capsys.readouterr().out
    assert (item / "manifest.json").stat().st_mtime_ns == mtime


def test_a_speed_setting_leaves_the_touch_items_hash_alone():
    """warp_gel's cpu_threads changes how fast touches are made, not the touches: an item's hash leaves it out, so
    finished items stay valid whatever it is set to; a setting that changes the touches changes the hash."""
    from omegaconf import OmegaConf

    from tnf.artifacts import config_hash
    from tnf.env import conf_dir
    from tnf.registry import SENSORS
    from tnf.stages.touch import item_config
    from tnf.testing import compose

    digit = SENSORS.build("digit")
    key = item_config(compose("touch"), digit)
    yaml = OmegaConf.to_container(OmegaConf.load(f"{conf_dir()}/simulator/warp_gel.yaml"))
    assert key["simulator"] == ("warp_gel", {k: v for k, v in yaml.items() if k not in ("name", "cpu_threads")})
    threads = item_config(compose("touch", ["simulator.cpu_threads=1"]), digit)
    assert config_hash(threads) == config_hash(key)
    falloff = item_config(compose("touch", ["simulator.falloff=0.6"]), digit)
    assert config_hash(falloff) != config_hash(key)


def test_lateral_offset_puts_a_balls_contacts_off_the_gels_centre(data_root):
    """A bearing ball's presses all land at the gel's centre; with touch.lateral_offset they spread over the gel,
    and the setting keys the item only when it is on."""
    from tnf.artifacts import config_hash
    from tnf.errors import TnfError
    from tnf.registry import SENSORS
    from tnf.stages.touch import item_config
    from tnf.testing import compose

    def offsets(extra):
        assert (
            main(
                [
                    "touch",
                    "debug=tiny",
                    "object=bearing_ball",
                    "sensor=gelsight_mini",
                    "progress=false",
                    "device=cpu",
                    *extra,
                ]
            )
            == 0
        )
        m = json.loads(
            (data_root / "touch" / "gelsight_mini" / "builtin" / "bearing_ball" / "manifest.json").read_text()
        )
        out = []
        for t in m["touches"]:
            c2w = np.array(t["contact_c2w"])
            local = c2w[:3, :3].T @ (np.array(t["contact_point"]) - c2w[:3, 3])  # contact in the sensor's frame
            out.append(local[:2])
        return np.array(out)

    mini = SENSORS.build("gelsight_mini")
    centred = offsets([])
    assert np.abs(centred).max() < 2e-4  # every press at the centre, to the gel grid's half cell
    spread = offsets(["touch.lateral_offset=1.0"])
    assert np.abs(spread[:, 0]).max() > 0.25 * mini.cfg.gel_width / 2
    assert np.abs(spread[:, 1]).max() > 0.25 * mini.cfg.gel_height / 2
    assert (np.abs(spread[:, 0]) <= mini.cfg.gel_width / 2 + 1e-4).all()
    key = item_config(compose("touch"), mini)
    assert config_hash(item_config(compose("touch", ["touch.lateral_offset=0.0"]), mini)) == config_hash(key)
    assert config_hash(item_config(compose("touch", ["touch.lateral_offset=0.5"]), mini)) != config_hash(key)
    with pytest.raises(TnfError, match="lateral_offset"):
        item_config(compose("touch", ["touch.lateral_offset=1.5"]), mini)
