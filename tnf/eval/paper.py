"""The paper's reported figures (mean, standard error), shown beside ours in the report.

Table 1 is the main simulated experiment (Digit), Table 2 the transfer to a simulated OmniTact sensor.
Keys: ``image[(test_set, method)] = {"ssim": (mean, se), "mse": (mean, se)}``, ``accuracy[row] = (mean, se)``
in percent. ``BG`` (the sensor's background image used as the prediction) has test set ``all``.
"""

from __future__ import annotations

from typing import TypedDict

Pair = tuple[float, float]


class PaperTable(TypedDict, total=False):
    """One table's figures: ``image[(test_set, method)][metric]`` and ``accuracy[row]``."""

    image: dict[tuple[str, str], dict[str, Pair]]
    accuracy: dict[str, Pair]


TABLE1_IMAGE: dict[tuple[str, str], dict[str, Pair]] = {
    ("novel_view", "T-N"): {"ssim": (0.980, 0.001), "mse": (14.5, 0.8)},
    ("novel_view", "Lee"): {"ssim": (0.678, 0.002), "mse": (1040.0, 10.0)},
    ("novel_view", "Cycle"): {"ssim": (0.649, 0.002), "mse": (1660.0, 10.0)},
    ("novel_object", "T-N"): {"ssim": (0.961, 0.000), "mse": (84.0, 3.0)},
    ("novel_object", "Lee"): {"ssim": (0.687, 0.001), "mse": (990.0, 10.0)},
    ("novel_object", "Cycle"): {"ssim": (0.660, 0.002), "mse": (1610.0, 10.0)},
    ("all", "BG"): {"ssim": (0.921, 0.000), "mse": (67.4, 3.0)},
}
TABLE1_ACCURACY: dict[str, Pair] = {
    "Sim": (85.0, 3.0),
    "Sim + T-N": (96.0, 2.0),
    "Sim + Lee": (86.0, 4.0),
    "Sim + Cycle": (80.0, 0.0),
}
TABLE2_IMAGE: dict[tuple[str, str], dict[str, Pair]] = {
    ("novel_view", "T-N"): {"ssim": (0.865, 0.002), "mse": (550.0, 10.0)},
    ("novel_view", "FS"): {"ssim": (0.829, 0.002), "mse": (950.0, 20.0)},
    ("novel_object", "T-N"): {"ssim": (0.839, 0.003), "mse": (760.0, 30.0)},
    ("novel_object", "T-N+"): {"ssim": (0.847, 0.003), "mse": (760.0, 30.0)},
    ("novel_object", "FS"): {"ssim": (0.811, 0.005), "mse": (1300.0, 60.0)},
    ("all", "BG"): {"ssim": (0.856, 0.001), "mse": (1390.0, 20.0)},
}
TABLE2_ACCURACY: dict[str, Pair] = {
    "Sim": (86.0, 0.0),
    "Sim + T-N": (94.0, 1.0),
    "Sim + FS": (82.0, 1.0),
}

PAPER: dict[str, PaperTable] = {
    "main": {"image": TABLE1_IMAGE, "accuracy": TABLE1_ACCURACY},
    "transfer": {"image": TABLE2_IMAGE, "accuracy": TABLE2_ACCURACY},
}

# Display label of each in-tree generator in the tables (the paper's names).
METHOD_LABELS = {"tn_cgan": "T-N", "lee": "Lee", "cyclegan": "Cycle"}
