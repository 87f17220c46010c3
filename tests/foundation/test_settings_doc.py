"""docs/settings.md's table of settings that change the results names real config keys, with the values they take by
default and in experiment=sim_digit, so the table cannot drift from the configs."""

from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from tnf.testing import compose

DOC = Path(__file__).resolve().parents[2] / "docs" / "settings.md"
SECTION = "# Settings that change the results"


def _value(cell: str, default: object = None) -> object:
    """A table cell as a config value: `[a, b]`, `contact`, 0.5, null, false; "the same" repeats ``default``."""
    if cell == "the same":
        return default
    return yaml.safe_load(cell.replace("`", ""))


def settings_rows() -> list[tuple[str, object, object]]:
    """(config key, default value, sim_digit value) for each key of each row of docs/settings.md's table."""
    text = DOC.read_text(encoding="utf-8")
    assert SECTION in text, f"docs/settings.md has no section {SECTION!r}"
    section = text.split(SECTION, 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        if not line.startswith("| `"):
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        keys = [k.split("=", 1)[0] for k in cells[0].replace("`", "").split(", ")]
        default = _value(cells[2])
        sim_digit = _value(cells[3], default)
        rows += [(key, default, sim_digit) for key in keys]
    return rows


ROWS = settings_rows()


def test_the_table_has_its_rows():
    keys = [key for key, _, _ in ROWS]
    assert len(keys) >= 9 and len(set(keys)) == len(keys)
    assert "evaluate.classifier.real_fraction" in keys and "generator.coords" in keys


@pytest.mark.parametrize("key, default, sim_digit", ROWS, ids=[key for key, _, _ in ROWS])
def test_readme_setting_matches_the_configs(key, default, sim_digit):
    missing = object()
    for overrides, stated in (([], default), (["experiment=sim_digit"], sim_digit)):
        value = OmegaConf.select(compose("train", overrides), key, default=missing)
        assert value is not missing, f"docs/settings.md names {key}, which the config does not have"
        if OmegaConf.is_config(value):
            value = OmegaConf.to_container(value)
        assert value == stated, (
            f"docs/settings.md says {key} is {stated!r} with {overrides or 'the defaults'}, config: {value!r}"
        )
