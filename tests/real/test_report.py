"""The realism report: rows of any size scored at the recording's size and at the sensor's, one table, one grid."""

import json

import numpy as np
import pytest
from PIL import Image

from tnf.real import realism, report
from tnf.real.presses import at_sensor_size
from tnf.registry import SENSORS

TEST = [16, 17, 18]


@pytest.fixture(scope="module")
def setup(taxim_presses):
    sensor = SENSORS.build("gelsight_mini")
    return taxim_presses, at_sensor_size(taxim_presses, sensor, TEST)


def test_rows_of_any_size_are_scored_against_the_real_frames(setup, tmp_path):
    presses, sp = setup
    real = np.stack([presses.frame(i) for i in TEST])  # 640x480
    small = report.resize(real, 160, 120)  # as a 160x120 generator would see them
    rows = [
        report.Row("the real frames", real),
        report.Row("real at 160x120", small, 0.01),
        report.Row("no contact", np.stack([presses.background()] * 3)),
    ]
    record = report.write_report(tmp_path, "title", ["an intro line"], rows, presses, sp, grid_presses=2)
    mean = record["mean"]
    assert list(mean) == [r.name for r in rows]
    assert mean["the real frames"]["ssim_crop"] == pytest.approx(1.0) and mean["the real frames"]["mse_crop"] == 0
    assert mean["the real frames"]["sharpness"] == pytest.approx(1.0)
    # Upsampled from 160x120, the frames lose their fine detail: less sharp, not equal, still far closer than f0.
    low = mean["real at 160x120"]
    assert 0.3 < low["sharpness"] < 0.95 and low["ssim_crop"] < 1
    assert low["mse_crop"] < mean["no contact"]["mse_crop"] and low["mse_region"] < mean["no contact"]["mse_region"]
    assert len(record["per_press"]["no contact"]["ssim_crop"]) == 3
    # The per-press figures match the crop score computed directly.
    c = np.array([presses.presses[i].center for i in TEST])
    r = np.array([presses.contact_radius_px(i) for i in TEST])
    direct = realism.crop_score(np.stack([presses.background()] * 3), real, c, r)
    assert record["per_press"]["no contact"]["mse_crop"] == pytest.approx(direct["mse_crop"])
    assert json.loads((tmp_path / "realism.json").read_text())["test"] == TEST
    text = (tmp_path / "realism.md").read_text()
    assert "| real at 160x120 | " in text and "| 10.0 |" in text and "an intro line" in text
    grid = Image.open(tmp_path / "realism.png")
    cell = round(4 * max(r[:2]) * 1.25) + 4  # a crop a quarter wider than the scored square, and its padding
    assert grid.size == (4 * cell, 18 + 2 * cell)  # real + three rows, two presses, a line of labels


def test_a_row_with_the_wrong_number_of_images_is_refused(setup, tmp_path):
    presses, sp = setup
    with pytest.raises(ValueError, match="has 2 images for 3 presses"):
        report.score_rows([report.Row("short", np.stack([presses.background()] * 2))], presses, sp)
